"""The drives as ROS joints: states, targets, commands and moves mapped onto the drive service.

- ``~/joint_states`` (``sensor_msgs/JointState``): every drive's position, velocity and effort
  in joint units, once per feedback cycle (every SYNC with ``sync.period``, else 50 Hz),
  stamped with the host's receive time of the newest feedback in it.
- ``~/node_<id>/drive_state`` (``cbcan_ros/DriveState``, reliable, transient local): on every
  change of state, mode, fault or halt.
- ``~/node_<id>/target`` (``std_msgs/Float64``) and ``~/joint_commands`` (``JointState``, by
  joint name): the target of each drive's present mode, in joint units. Subscribed best
  effort, so that every publisher matches (a reliable one too); the newest target is what
  counts, and the command timeout catches a stream that stops.
- ``~/drive_command`` (``cbcan_ros/DriveCommand``) and the action ``~/move``
  (``cbcan_ros/DriveMove``), answered when the drive's statusword shows the result.

``~/joint_states`` and ``~/joint_commands`` are what ros2_control's topic-based hardware
interface publishes and reads, so the joints can run under ros2_control controllers.
"""

from concurrent.futures import Future
import logging
import math
import re
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future as RclpyFuture
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from ..action import DriveMove
from ..core.drives import cia402
from ..core.drives.checks import target_value_problem
from ..core.drives.service import DriveService
from ..core.drives.status import DriveResult, DriveStatus, failed
from ..core.text import HEARTBEAT_SILENT, SHUTTING_DOWN
from ..core.values import int_given_as_float
from ..msg import DriveState
from .drive_parameters import Joint
from .goals import GoalCallbacks, KeptActionServer
from .pdo import stamp_of

LOGGER = logging.getLogger(__name__)

# How long drive state changes wait to be published, for the commands woken with them.
YIELD_TO_COMMANDS = 0.001

STATE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
JOINT_STATES_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
TARGET_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
# The incidents of refusals that concern no one drive (no drive has node id 0 or -1): the
# gateway's (inactive, shutting down), and joints a message names that are no drive's (a
# message may name joints of other hardware in every message: logged once, not again).
GATEWAY_WIDE = 0
OTHER_HARDWARE = -1
# A refusal's kind, as logged once an incident: a drive that passes through states as it
# stops is refused for one reason, whichever state it shows, and numbers aside.
_STATES_AND_NUMBERS = re.compile('|'.join(sorted(
    [name for name, *_ in cia402.STATES] + [cia402.UNKNOWN], key=len, reverse=True))
    + r'|[-\d.e+]+')


def _field(mode: Optional[int]) -> Optional[str]:
    """Return the JointState field a drive in ``mode`` takes, None for none."""
    return {cia402.TARGET_POSITION: 'position', cia402.TARGET_VELOCITY: 'velocity',
            cia402.TARGET_TORQUE: 'effort'}.get(cia402.TARGET_OF_MODE.get(mode))


def fill_command(result: DriveResult, response) -> None:
    """Write a DriveResult into a ``DriveCommand`` response."""
    status = result.status
    response.success = result.success
    response.message = result.message
    response.state = status.state
    response.statusword = status.statusword
    response.mode = status.mode
    response.error_code = status.error_code
    response.abort_code = result.abort_code


class DriveTopics:
    """The topics and the move action of the drives of ``service``, by joint.

    ``refusal()`` returns why the node takes no request now (inactive), or None.
    """

    def __init__(self, node: Node, service: DriveService, joints: Dict[int, Joint],
                 refusal: Callable[[], Optional[str]]):
        self._node = node
        self._service = service
        self._joints = joints
        self._by_name = {joint.name: joint for joint in joints.values()}
        self._refusal = refusal
        self._logged: Dict[Optional[int], set] = {}  # kinds of refusal logged, by node
        self._cancels: Dict[bytes, Callable[[], None]] = {}
        self._states = {node_id: node.create_publisher(
            DriveState, f'~/node_{node_id}/drive_state', STATE_QOS) for node_id in joints}
        self._joint_states = (node.create_publisher(JointState, '~/joint_states',
                                                    JOINT_STATES_QOS) if joints else None)
        self._subscriptions = [
            node.create_subscription(Float64, f'~/node_{node_id}/target',
                                     lambda message, n=node_id: self._on_target(n, message),
                                     TARGET_QOS)
            for node_id in joints]
        if joints:
            self._subscriptions.append(node.create_subscription(
                JointState, '~/joint_commands', self._on_joint_commands, TARGET_QOS))
        self._action = KeptActionServer.of(node, DriveMove, '~/move')
        self._action.attach(GoalCallbacks(self._execute_move, self._cancels))
        # Changes are published by a thread of their own, not by the bus thread that sees
        # them: every change told, in order, then the newest if one was told late.
        self._changed: List[DriveStatus] = []
        self._wake = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._publish_changes, name='drive states',
                                        daemon=True)
        self._thread.start()
        service.add_listener(self._on_change)
        service.add_cycle_listener(self._publish_joint_states)
        self.publish_states()

    def destroy(self) -> None:
        """Stop publishing and take the topics and the action away (after the bus closed)."""
        with self._wake:
            self._closing = True
            self._wake.notify()
        self._thread.join(timeout=2.0)
        self._action.detach()
        for publisher in [*self._states.values(), self._joint_states]:
            if publisher is not None:
                self._node.destroy_publisher(publisher)
        for subscription in self._subscriptions:
            self._node.destroy_subscription(subscription)

    def publish_states(self) -> None:
        """Publish every drive's state as it is now (a managed node just activated)."""
        for status in self._service.statuses():
            self._on_change(status)

    def start_command(self, request) -> 'Future[DriveResult]':
        """Run a ``DriveCommand`` request; the future resolves to its answer."""
        refusal = self._refusal()
        if refusal:
            future: Future = Future()
            future.set_result(failed(DriveStatus(request.node_id), refusal, 0x08000022))
            return future
        return self._service.command(request.node_id, request.command, request.mode,
                                     request.timeout)

    # Publishing.

    def _on_change(self, status: DriveStatus) -> None:
        with self._wake:
            self._changed.append(status)
            self._wake.notify()

    def _publish_changes(self) -> None:
        while True:
            with self._wake:
                while not self._changed and not self._closing:
                    self._wake.wait()
                if self._closing:
                    return
            # The statusword that told this change also woke the command waiting for it
            # (an enable's next step, a command's answer): that goes first, publishing a
            # moment later; a step took a third longer while both contended for the GIL.
            time.sleep(YIELD_TO_COMMANDS)
            with self._wake:
                if self._closing:
                    return
                changed, self._changed = self._changed, []
            if self._refusal() is None:
                last = {}
                for status in changed:
                    self._states[status.node_id].publish(self._state_message(status))
                    last[status.node_id] = status
                # Changes are told in order, but an activation's snapshot (publish_states)
                # may be queued after a newer change: the newest must be published last.
                for node_id, status in last.items():
                    now = self._service.status(node_id)
                    if now.told != status.told:
                        self._states[node_id].publish(self._state_message(now))

    def _state_message(self, status: DriveStatus) -> DriveState:
        joint = self._joints[status.node_id]
        return DriveState(
            stamp=stamp_of(status.received) if status.received else
            self._node.get_clock().now().to_msg(),
            node_id=status.node_id, joint=joint.name, state=status.state,
            statusword=status.statusword, mode=status.mode,
            position=float(joint.position(status.position)),
            velocity=float(joint.velocity(status.velocity)),
            effort=float(joint.effort(status.torque)), error_code=status.error_code,
            error=status.error, target_reached=status.target_reached, halted=status.halted)

    def _publish_joint_states(self) -> None:
        wanted = (self._joint_states is not None and self._refusal() is None
                  and self._joint_states.get_subscription_count() > 0)
        self._service.want_cycle_statuses(wanted)
        if not wanted:
            return  # volatile: a message nobody receives is not worth building
        statuses = self._service.cycle_statuses()
        newest = max(status.received for status in statuses)
        message = JointState()
        message.header.stamp = (stamp_of(newest) if newest
                                else self._node.get_clock().now().to_msg())
        joints = [self._joints[status.node_id] for status in statuses]
        message.name = [joint.name for joint in joints]
        message.position = [float(joint.position(s.position))
                            for joint, s in zip(joints, statuses, strict=True)]
        message.velocity = [float(joint.velocity(s.velocity))
                            for joint, s in zip(joints, statuses, strict=True)]
        message.effort = [float(joint.effort(s.torque))
                          for joint, s in zip(joints, statuses, strict=True)]
        self._joint_states.publish(message)

    # Targets.

    def _on_target(self, node_id: int, message: Float64) -> None:
        topic = f'node_{node_id}/target'
        problem = int_given_as_float('target', message.data)
        if problem:  # a JointState's arrays take ints as they are: only this field
            self._log_refusal(f'{topic}: {problem}; nothing was sent', node_id)
            return
        self._send_target(self._joints[node_id], message.data, topic)

    def _on_joint_commands(self, message: JointState) -> None:
        refusal = self._refusal()
        if refusal:
            self._log_refusal(f'joint_commands: {refusal}', GATEWAY_WIDE)
            return
        targets = self._targets_of(message)
        drives = sum(1 for name in message.name if name in self._by_name)
        taken = bool(targets) and len(targets) == drives
        # One message, one SYNC cycle: no drive takes its target a cycle after another.
        with self._service.one_cycle():
            for joint, value in targets:
                taken = self._deliver(joint, value, 'joint_commands') and taken
        if taken:  # every drive named took its value: a problem of whole messages is over
            self._logged.pop(None, None)
            if drives == len(message.name):  # and no joint of other hardware is named
                self._logged.pop(OTHER_HARDWARE, None)

    def _targets_of(self, message: JointState) -> List[Tuple[Joint, float]]:
        """Return the (joint, value in drive units) of a ``joint_commands`` message; log the rest.

        ros2_control's topic-based hardware interface fills each array only for the joints
        that have that command interface: with mixed interfaces, a shorter array holds the
        values of the joints taking it, in the order of the names. Which joint takes which
        is told by the drives' modes, only when every name is a drive's in a mode that
        takes a target and the array has as many values as those drives. A message with a
        value that is no target (not finite, too large) is refused whole: the joints of an
        arm apply one control step together or not at all.
        """
        names = message.name
        if not names:
            self._log_refusal('joint_commands: a message names no joint, so its values are '
                              "no drive's; nothing was sent")
            return []
        if len(set(names)) != len(names):
            twice = sorted({name for name in names if names.count(name) > 1})
            # Two values for one drive: whichever frame the drive takes last would win.
            self._log_refusal(f'joint_commands: joint {twice[0]!r} is named more than once '
                              f'in the message; which value is its cannot be told, so nothing '
                              f'of the message was sent')
            return []
        joints = [self._by_name.get(name) for name in names]
        modes = [self._service.status(joint.node_id).mode if joint else None
                 for joint in joints]
        fields = [_field(mode) for mode in modes]
        arrays = {field: getattr(message, field) for field in set(fields) if field}
        known = all(fields)
        targets, unclear = [], []
        for n, (name, joint, field) in enumerate(zip(names, joints, fields, strict=True)):
            if joint is None:
                self._log_refusal(f"joint_commands: joint {name!r} is no drive's (joints: "
                                  f'{", ".join(self._by_name) or "none"}); left out',
                                  OTHER_HARDWARE)
                continue
            values = arrays[field] if field else ()
            if field and len(values) == len(names):
                targets.append((joint, values[n]))
                continue
            taking = [k for k, other in enumerate(fields) if other == field]
            if field and known and len(values) == len(taking):
                targets.append((joint, values[taking.index(n)]))
            elif field:
                unclear.append(f'{name!r} ({cia402.mode_name(modes[n])}: {field})')
            else:
                self._log_refusal(f'joint_commands: joint {name!r} (node {joint.node_id}) '
                                  f'{self._takes_none(joint)}; nothing was sent',
                                  joint.node_id)
        if unclear:
            counts = ', '.join(f'{len(getattr(message, field))} {field}'
                               for field in ('position', 'velocity', 'effort'))
            self._log_refusal(f'joint_commands: the message names {len(names)} joints '
                              f'and has {counts} values; which value is whose cannot be told '
                              f'for joints {", ".join(unclear)}; nothing was sent to them',
                              kind=f'unclear: {", ".join(unclear)}')  # each set of joints
        mode_of = {joint.node_id: mode for joint, mode in zip(joints, modes, strict=True)
                   if joint}
        in_drive_units = []
        for joint, value in targets:
            mode = mode_of[joint.node_id]
            device = joint.to_device(mode, value)
            problem = (f'{value} is not a finite number' if not math.isfinite(value)
                       else target_value_problem(mode, device))
            if problem:
                self._log_refusal(f'joint_commands: joint {joint.name!r} (node '
                                  f'{joint.node_id}): {problem}; nothing of the message was '
                                  f'sent')
                return []
            in_drive_units.append((joint, device))
        return in_drive_units

    def _takes_none(self, joint: Joint) -> str:
        """Return why a drive in no mode that takes a target takes none, for the log."""
        status = self._service.status(joint.node_id)
        if status.state != cia402.OPERATION_ENABLED:
            state = ('not heard (UNKNOWN)' if status.state == cia402.UNKNOWN
                     else f'{status.state}, not enabled')
            return f'is {state}, so it takes no target'
        return f'is in {cia402.mode_name(status.mode)}, which takes no target'

    def _send_target(self, joint: Joint, value: float, topic: str) -> bool:
        """Send a target in joint units to the joint's drive; log why not (return if it went)."""
        refusal = self._refusal()
        if refusal:
            self._log_refusal(f'{topic}: {refusal}', GATEWAY_WIDE)
            return False
        if not math.isfinite(value):
            self._log_refusal(f'{topic}: target {value} for node {joint.node_id} is not a '
                              f'finite number; nothing was sent', joint.node_id)
            return False
        mode = self._service.status(joint.node_id).mode
        return self._deliver(joint, joint.to_device(mode, value), topic)

    def _deliver(self, joint: Joint, value: float, topic: str) -> bool:
        """Send a target in drive units to the joint's drive; log why not (return if it went)."""
        result = self._service.target(joint.node_id, value)
        if not result.success:
            # Shutting down, or held up too long, concerns no drive: one line, not one a drive.
            gateway_wide = SHUTTING_DOWN in result.message or HEARTBEAT_SILENT in result.message
            self._log_refusal(f'{topic}: {result.message}',
                              GATEWAY_WIDE if gateway_wide else joint.node_id)
            return False
        for incident in (joint.node_id, GATEWAY_WIDE):  # over: the next one is logged
            self._logged.pop(incident, None)
        return True

    def _log_refusal(self, problem: str, node_id: Optional[int] = None,
                     kind: Optional[str] = None) -> None:
        """Log a refused target once per kind (numbers and states aside) and incident.

        A stream of refused targets is one line, not a log flood; once the drive ``node_id``
        takes a target again, its next refusal is a new incident and logged again. Those of
        a whole ``joint_commands`` message (``node_id`` None: its names or values) end once a
        message's drives all take theirs; those of the gateway (``GATEWAY_WIDE``: inactive,
        shutting down) once any target is taken; joints of other hardware
        (``OTHER_HARDWARE``) once a message names only drives and is taken whole. ``kind``:
        what makes two problems the same, where the text alone does not tell (joint names
        that differ only in their digits).
        """
        kind = kind or _STATES_AND_NUMBERS.sub('#', problem)[:100]
        logged = self._logged.setdefault(node_id, set())
        if kind not in logged:
            logged.add(kind)
            until = ('until a message is taken whole' if node_id is None
                     else 'until a target is taken' if node_id == GATEWAY_WIDE
                     else 'until a message names only drives' if node_id == OTHER_HARDWARE
                     else f'until node {node_id} takes a target again')
            LOGGER.warning('%s (later ones like it are not logged %s)', problem, until)

    # The move action.

    def _refused_move(self, goal_handle, joint: Optional[Joint], refusal: str):
        """Abort a move refused before anything was sent; its result says where the drive is.

        NaN for a node that is not a drive (nothing is known of it).
        """
        goal_handle.abort()
        status = self._service.status(joint.node_id) if joint is not None else None
        return DriveMove.Result(
            success=False, message=refusal,
            position=float(joint.position(status.position)) if status else math.nan,
            error_code=status.error_code if status else 0)

    async def _execute_move(self, goal_handle):
        goal = goal_handle.request
        joint = self._joints.get(goal.node_id)
        refusal = self._refusal()
        if refusal is None and joint is None:
            refusal = (f'node {goal.node_id} is not a drive (parameter drives.nodes: '
                       f'{sorted(self._joints) or "none"}); nothing was sent')
        if refusal is None and not (math.isfinite(goal.position)
                                    and math.isfinite(goal.velocity)):
            refusal = (f'position {goal.position} and velocity {goal.velocity} must be '
                       f'finite numbers; nothing was sent')
        if refusal is None:
            refusal = next(filter(None, (int_given_as_float(name, getattr(goal, name))
                                         for name in ('position', 'velocity', 'timeout'))), None)
            refusal = refusal and f'{refusal}; nothing was sent'
        if refusal is None and not (math.isfinite(goal.timeout) and goal.timeout >= 0):
            refusal = (f'timeout {goal.timeout} must be 0 (the default, 60 s) or more '
                       f'seconds; nothing was sent')
        if refusal is None and goal.velocity < 0:
            refusal = (f"velocity {goal.velocity} must be 0 (the drive's profile velocity, "
                       f'0x6081) or more: the position gives the direction; nothing was sent')
        if refusal:
            return self._refused_move(goal_handle, joint, refusal)
        position = joint.to_device(cia402.PROFILE_POSITION, goal.position, goal.relative)
        velocity = abs(goal.velocity * joint.velocity_scale)  # the scale may flip the axis
        if not (math.isfinite(position) and math.isfinite(velocity)):
            return self._refused_move(goal_handle, joint, (
                f'position {goal.position} or velocity {goal.velocity} does not fit the '
                f"drive's units (node_{joint.node_id} scales); nothing was sent"))
        if goal.velocity and velocity < 1:
            # 0 would be the drive's own profile velocity: a slow move must not run at that.
            return self._refused_move(goal_handle, joint, (
                f'velocity {goal.velocity} is {velocity:g} counts/s at '
                f'node_{joint.node_id}.velocity_scale {joint.velocity_scale:g}: below the 1 '
                f'count/s a drive takes (0 means its profile velocity); nothing was sent'))

        def feedback(status: DriveStatus) -> None:
            goal_handle.publish_feedback(DriveMove.Feedback(
                position=float(joint.position(status.position)),
                velocity=float(joint.velocity(status.velocity))))

        future, cancel = self._service.move(joint.node_id, round(position), goal.relative,
                                            round(velocity), feedback, goal.timeout)
        key = bytes(goal_handle.goal_id.uuid)
        self._cancels[key] = cancel
        done = RclpyFuture()
        future.add_done_callback(lambda finished: done.set_result(finished.result()))
        try:
            result = await done
        finally:
            self._cancels.pop(key, None)
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return DriveMove.Result(success=result.success, message=result.message,
                                position=float(joint.position(result.status.position)),
                                error_code=result.status.error_code)

