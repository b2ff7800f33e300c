"""The QoS of the gateway's services and of its actions' services."""

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
