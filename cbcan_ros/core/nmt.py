"""NMT: command codes, node states, and the heartbeat monitor that knows every node's state.

States are only ever what a node itself reported (heartbeat, boot-up message or node guarding
reply); a node silent for longer than the heartbeat timeout is NOT_DETECTED. canopen's
``NmtMaster`` tracks state only for nodes added to the network and never times out, so the
monitor subscribes to every heartbeat COB-ID itself and runs its own timeout watch.
"""

from dataclasses import dataclass
import math
import threading
import time
from typing import Callable, Dict, Iterable, List, Optional

from .bus import prompt, wall_clock

HEARTBEAT_COB_BASE = 0x700

BOOT_UP = 0
STOPPED = 4
OPERATIONAL = 5
NOT_DETECTED = 6
PRE_OPERATIONAL = 127

STATE_NAMES = {
    BOOT_UP: 'BOOT_UP',
    STOPPED: 'STOPPED',
    OPERATIONAL: 'OPERATIONAL',
    NOT_DETECTED: 'NOT_DETECTED',
    PRE_OPERATIONAL: 'PRE_OPERATIONAL',
}

START = 1
STOP = 2
ENTER_PRE_OPERATIONAL = 128
RESET_NODE = 129
RESET_COMMUNICATION = 130

COMMAND_NAMES = {
    START: 'START',
    STOP: 'STOP',
    ENTER_PRE_OPERATIONAL: 'ENTER_PRE_OPERATIONAL',
    RESET_NODE: 'RESET_NODE',
    RESET_COMMUNICATION: 'RESET_COMMUNICATION',
}


def consumer_entry(producer_id: int, milliseconds: int) -> int:
    """Return a heartbeat consumer entry (0x1016:n, CiA 301): whose heartbeat, for how long.

    ``milliseconds`` above the entry's 16 bits is the longest it holds, 65535.
    """
    return producer_id << 16 | min(milliseconds, 0xFFFF)


def state_name(state: int) -> str:
    """Return the name of an NMT state byte, or 'UNKNOWN_<n>' for one CiA 301 does not define."""
    return STATE_NAMES.get(state, f'UNKNOWN_{state}')


def reported_state_name(state: int) -> str:
    """Return the name of a state byte a node sent; 6 is no CiA 301 state, so UNKNOWN_6.

    NOT_DETECTED (6) is the gateway's own word for a silent node: a node that sent 6 has
    spoken, so it is not "not detected".
    """
    return f'UNKNOWN_{state}' if state == NOT_DETECTED else state_name(state)


@dataclass(frozen=True)
class NodeStatus:
    """What is known of one node: its last reported state and when it last spoke.

    ``state`` is NOT_DETECTED while the node is silent, else the state byte it reported.
    """

    node_id: int
    state: int
    last_seen: Optional[float]  # time.time() of the last message; None if never seen
    last_seen_age: float        # seconds since then; -1 if never seen
    detected: bool = False

    @property
    def state_name(self) -> str:
        """Return the state's name, e.g. 'OPERATIONAL'."""
        return reported_state_name(self.state) if self.detected else 'NOT_DETECTED'


class _Entry:
    __slots__ = ('state', 'detected', 'last_monotonic', 'last_wall')

    def __init__(self):
        self.state = NOT_DETECTED
        self.detected = False
        self.last_monotonic: Optional[float] = None
        # Its time on the wall clock, worked out when first asked (not for every frame),
        # then kept: one heartbeat has one time, however often it is asked for.
        self.last_wall: Optional[float] = None


class HeartbeatMonitor:
    """Tracks the NMT state of every node that sends heartbeats, boot-ups or guarding replies.

    Listeners are called (from a bus or watcher thread, without locks held) whenever a node
    appears, changes state, or times out. Node ids in ``ignored`` (the gateway's own
    heartbeat) are not listened to.
    """

    def __init__(self, network, timeout: float, expected_nodes: Iterable[int] = (),
                 ignored: Iterable[int] = ()):
        self._network = network
        ignored = set(ignored)
        self._heard_ids = [node_id for node_id in range(1, 128) if node_id not in ignored]
        self._timeout = timeout
        self._timeouts: Dict[int, Optional[float]] = {}  # node: its own (None: not by time)
        self._nodes: Dict[int, _Entry] = {node_id: _Entry() for node_id in expected_nodes}
        self._listeners: List[Callable[[], None]] = []
        self._lost_at = float('-inf')  # when the bus last went down (time.monotonic())
        self._commanded: Dict[int, float] = {}  # node id (0 = all): when told to leave OP
        # Heartbeats take the plain lock (cheaper than entering the Condition, and every
        # frame pays for it); the watcher waits on the Condition built on it.
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._running = False
        self._watcher = threading.Thread(target=self._watch, name='heartbeat-timeouts',
                                         daemon=True)

    def set_timeouts(self, timeouts: Dict[int, Optional[float]]) -> None:
        """Give nodes a silence (s) of their own after which they are lost (before ``start``).

        None: the node is never lost by silence (it sends no heartbeat and is not guarded).
        """
        with self._lock:
            self._timeouts = dict(timeouts)

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every change of the picture."""
        self._listeners.append(listener)

    def start(self) -> None:
        """Listen to every heartbeat COB-ID and start watching for timeouts."""
        for node_id in self._heard_ids:
            self._network.subscribe(HEARTBEAT_COB_BASE + node_id, self._on_frame)
        self._running = True
        self._watcher.start()

    def stop(self) -> None:
        """Stop listening and watching."""
        for node_id in self._heard_ids:
            self._network.unsubscribe(HEARTBEAT_COB_BASE + node_id, self._on_frame)
        with self._changed:
            self._running = False
            self._changed.notify_all()
        if self._watcher.is_alive():
            self._watcher.join()

    def status(self, node_id: int) -> NodeStatus:
        """Return what is known of ``node_id`` (NOT_DETECTED if never seen)."""
        with self._changed:
            return self._status(node_id, self._nodes.get(node_id) or _Entry(), time.monotonic())

    def commanded(self, node_id: int, command: int) -> None:
        """Note that the gateway just sent ``node_id`` (0 = every node) NMT ``command``.

        A command that leaves OPERATIONAL (stop, pre-operational, a reset) takes the node
        off its PDOs at once, though its next heartbeat saying so may be a second away.
        """
        if command == START:
            return  # PDOs flow once the node says OPERATIONAL, as ever
        with self._changed:
            self._commanded[node_id] = time.monotonic()

    def operational(self, node_id: int) -> bool:
        """Return whether ``node_id`` said OPERATIONAL since a command that left that state.

        Its PDOs are usable then (see ``commanded``).
        """
        with self._lock:  # not the Condition: asked for every frame a drive is sent
            entry = self._nodes.get(node_id)
            left = max(self._commanded.get(node_id, -math.inf), self._commanded.get(0, -math.inf))
            return (entry is not None and entry.detected and entry.state == OPERATIONAL
                    and entry.last_monotonic > left)

    def statuses(self) -> List[NodeStatus]:
        """Return every known node (expected or seen), sorted by node id."""
        with self._changed:
            now = time.monotonic()
            return [self._status(node_id, entry, now)
                    for node_id, entry in sorted(self._nodes.items())]

    @staticmethod
    def _status(node_id: int, entry: _Entry, now: float) -> NodeStatus:
        state = entry.state if entry.detected else NOT_DETECTED
        if entry.last_monotonic is None:
            return NodeStatus(node_id, state, None, -1.0, entry.detected)
        if entry.last_wall is None:
            entry.last_wall = wall_clock(entry.last_monotonic)
        return NodeStatus(node_id, state, entry.last_wall, now - entry.last_monotonic,
                          entry.detected)

    @prompt
    def _on_frame(self, can_id: int, data: bytearray, stamp: float) -> None:
        """Take a heartbeat, boot-up or guarding reply received at ``stamp`` (monotonic)."""
        if not data:
            return
        node_id = can_id - HEARTBEAT_COB_BASE
        state = data[0] & 0x7F  # bit 7 is the node guarding toggle bit
        with self._lock:
            if stamp <= self._lost_at:
                return  # heard before the bus went down: it says nothing of the node now
            entry = self._nodes.get(node_id)
            is_new = entry is None
            if is_new:
                entry = self._nodes[node_id] = _Entry()
            changed = is_new or not entry.detected or entry.state != state
            entry.state = state
            entry.detected = True
            entry.last_monotonic = stamp
            entry.last_wall = None
            if changed:
                self._changed.notify_all()
        if changed:
            self._notify()

    def lose_all(self) -> None:
        """Report every node NOT_DETECTED (the bus is down: nothing can be heard)."""
        with self._changed:
            self._lost_at = time.monotonic()
            lost = [entry for entry in self._nodes.values() if entry.detected]
            for entry in lost:
                entry.detected = False
        if lost:
            self._notify()

    def _watch(self) -> None:
        with self._changed:
            while self._running:
                now = time.monotonic()
                timed_out = False
                next_deadline = None
                for node_id, entry in self._nodes.items():
                    timeout = self._timeouts.get(node_id, self._timeout)
                    if not entry.detected or timeout is None:
                        continue
                    deadline = entry.last_monotonic + timeout
                    if deadline <= now:
                        entry.detected = False
                        timed_out = True
                    elif next_deadline is None or deadline < next_deadline:
                        next_deadline = deadline
                if timed_out:
                    self._changed.release()
                    try:
                        self._notify()
                    finally:
                        self._changed.acquire()
                    continue
                self._changed.wait(None if next_deadline is None else next_deadline - now)

    def _notify(self) -> None:
        for listener in self._listeners:
            listener()


class NodeGuarding:
    """Polls nodes without a heartbeat producer by node guarding (RTR on 0x700 + id).

    Their replies arrive on the heartbeat COB-ID and are tracked by the monitor like
    heartbeats; the state byte's toggle bit is masked there. The polling runs on a thread of
    its own and survives failed sends (the bus supervisor reports and repairs the bus), so
    guarding resumes by itself when the bus comes back.
    """

    def __init__(self, network, node_ids: Iterable[int], period: float):
        self._network = network
        self._node_ids = sorted(set(node_ids))
        self._period = period
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._poll, name='node-guarding', daemon=True)

    def start(self) -> None:
        """Start polling the guarded nodes, if any."""
        if self._node_ids:
            self._thread.start()

    def stop(self) -> None:
        """Stop polling."""
        self._stopped.set()
        if self._thread.is_alive():
            self._thread.join()

    def _poll(self) -> None:
        while True:
            for node_id in self._node_ids:
                try:
                    self._network.send_message(HEARTBEAT_COB_BASE + node_id, b'', remote=True)
                except Exception:  # noqa: BLE001, S112 - the bus supervisor reports faults
                    continue
            if self._stopped.wait(self._period):
                return
