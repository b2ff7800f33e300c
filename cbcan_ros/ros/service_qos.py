"""The QoS of the gateway's services and of its actions' services, and how long results stay."""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# The default service QoS keeps 10 requests: a burst of calls (one per device, say) loses
# the oldest before the executor takes them. A deep history keeps every request of a burst
# (a full device queue is answered "busy"). Not keep-all: the answers share one history, and
# a client killed mid-call stays matched until its DDS lease ends (about 20 s) without ever
# acknowledging, so under keep-all its unacknowledged answers filled the history and every
# later answer to everyone failed. Clients sending bursts need a history this deep too.
SERVICE_DEPTH = 4096
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SERVICE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

# An action's goal, cancel and result requests are services too: at ROS's default depth a
# burst of goals lost all but the first few (50 of 300 goal responses came), each a goal
# never answered.
ACTION_SERVICES_QOS = dict(goal_service_qos_profile=SERVICE_QOS,
                           result_service_qos_profile=SERVICE_QOS,
                           cancel_service_qos_profile=SERVICE_QOS)

# How long, in seconds, an action server keeps a goal after it ended, to answer a result request
# that comes late (rclpy's default: 900 s). Every goal kept is listed in each status message
# the server publishes, and it publishes one at each goal's every change: with goals sent a few
# a second, the executor's time per goal grew with every goal of the last quarter of an hour
# (measured: 250 move goals cost the node 0.3 s of CPU at first, 1.4-2.1 s once 2,000-3,000
# were kept) until calls waited behind it for seconds. A client asks for the result as the goal
# is accepted (rclpy's and rclcpp's clients do): it is sent when the goal ends, however long
# that takes. Asked for later than this, a result comes back with status UNKNOWN.
ACTION_RESULT_KEPT = 10
