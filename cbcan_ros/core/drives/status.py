"""What the gateway knows of its CiA 402 drives: settings, status, answers, the record kept.

Shared by the drive service (``drive``), its sequences (``commands``) and its checks
(``checks``); the ROS layer reads :class:`DriveStatus` and :class:`DriveResult`.
"""

from dataclasses import dataclass, field, replace
import threading
from typing import Callable, Dict, List, Optional, Set, Tuple

from . import cia402
from .objects import DriveObjects


@dataclass(frozen=True)
class DriveSettings:
    """How the gateway runs its drives (the ROS node fills it from ``drives.*``)."""

    node_ids: Tuple[int, ...] = ()
    command_timeout: float = 0.5  # s without a target before a streaming drive is halted
    on_shutdown: str = 'quick_stop'
    consumer_time: float = 0.0  # s; with heartbeat_node_id, written to each drive's 0x1016
    heartbeat_node_id: int = 0
    # 0x6007 written to a drive that has 0 there (no reaction to a lost heartbeat); 0 = not
    # written, enable refused instead; None = the drives do not watch the gateway.
    abort_connection: Optional[int] = None
    # The target torque that holds each drive in PT and CST (drive units), by node id.
    hold_torques: Dict[int, int] = field(default_factory=dict)
    feedback_period: float = 0.02  # s between feedback cycles (the SYNC period with SYNC)


@dataclass(frozen=True)
class DriveStatus:
    """What the gateway knows of one drive now; values in the drive's own units."""

    node_id: int
    state: str = cia402.UNKNOWN
    statusword: int = 0
    mode: int = 0  # 0x6061, the mode the drive is in
    position: int = 0
    velocity: int = 0
    torque: int = 0
    error_code: int = 0
    received: float = 0.0  # time.monotonic() of the last feedback; 0 = none yet
    halted: bool = False
    needs_enable: bool = True  # targets are refused until an enable succeeds
    changing_mode: bool = False  # why, meanwhile: a set_mode runs (targets wait for it)
    supported_modes: int = 0  # 0x6502; 0 = not read

    @property
    def error(self) -> str:
        """Return the meaning of the error code, '' without one."""
        return cia402.error_meaning(self.error_code) if self.error_code else ''

    @property
    def target_reached(self) -> bool:
        """Return statusword bit 10."""
        return bool(self.statusword & cia402.TARGET_REACHED)

    @property
    def told(self) -> tuple:
        """Return the fields a change of which is told (and published): state, mode, error."""
        return (self.state, self.mode, self.error_code, self.target_reached, self.halted)

    @property
    def faulted(self) -> bool:
        """Return whether the drive is in FAULT or its fault reaction."""
        return self.state in cia402.FAULTED


@dataclass(frozen=True)
class DriveResult:
    """The one answer to a drive command or move."""

    success: bool
    message: str
    status: DriveStatus
    abort_code: int = 0


@dataclass
class DriveRecord:
    """A drive's mutable state, guarded by the service's lock."""

    node_id: int
    objects: DriveObjects
    status: DriveStatus
    heard: bool = False  # heartbeat seen since it was last lost
    read_wanted: int = 0  # initial reads asked for (first heard, each boot)
    read_done: int = 0  # the request the values answer; negative: that one failed
    read_failed_at: float = 0.0
    ready: int = 0  # the initial read whose every step (stop, consumer) is done: commands go
    unread_state: str = ''  # the state its TPDOs show while it is not re-read yet
    updates: int = 0  # statuswords taken: a waiter asks for one newer than it sent
    tpdos: int = 0  # TPDOs with feedback taken: an SDO read asked after the n-th is newer
    from_tpdo: Dict[int, Tuple[int, int]] = field(default_factory=dict)  # index: (n, value)
    _controlword: int = 0  # the controlword the gateway commands (``controlword``)
    halted_by: str = ''  # '', 'command' or 'timeout'
    last_target: float = 0.0
    polling: bool = False
    polled: float = 0.0  # time.monotonic() of the last SDO read of its feedback
    # What TPDOs brought at that read: (object, mapping read it came by).
    polled_mapped: Set[Tuple[int, int]] = field(default_factory=set)
    timeouts: int = 0
    halt_failing: bool = False  # the command timeout's last halt could not be sent
    # Why the last set-point of the last stream of PP set-points was not reached, or ''.
    missed_set_point: str = ''
    emcy_code: int = 0  # the error code of the last EMCY
    lost_powered: bool = False  # its heartbeat stopped while its power stage was on
    position_window: Optional[int] = None  # 0x6067 in drive units, once read (arrival)
    velocity_threshold: Optional[int] = None  # 0x606F, once read; 0: the drive has none
    position_limits: Optional[tuple] = None  # 0x607D (min, max); () none; None not read yet
    profile_velocity: int = 0  # 0x6081 as read when heard: what a move with velocity 0 uses
    pp_goal: Optional[int] = None  # the last PP set-point given since its enable: relative base
    unwatched: str = ''  # why it would run on if the gateway died (enable refused), or ''
    enabling: bool = False  # an enable runs on the drives' loop (what a refusal says meanwhile)
    # A mode the gateway wrote (0x6060) that the drive has not shown yet: a sequence ended
    # (failed, replaced) before it did, and the write may still land.
    mode_pending: Optional[int] = None
    # Ends once the frames of its last command step sent in synchronous RPDOs are applied (an
    # asyncio task of the drives' loop; None: none sent).
    applied_at_sync: Optional[object] = None
    waiters: List[Callable[[], None]] = field(default_factory=list)
    # Held from deciding what to send (a target, a halt, a stop, a step) until it is handed
    # to the bus: the drive gets frames in the order they were decided. Taken before the
    # service's lock, never while holding it.
    sending: threading.Lock = field(default_factory=threading.Lock)
    # The drive left OPERATION_ENABLED by itself (the gateway still commanding "enable
    # operation") and the gateway decided no controlword since: back in OPERATION_ENABLED,
    # it runs again unasked (a frame it held for SYNC with the controlword that ran it:
    # transition 16 from QUICK_STOP_ACTIVE; another master).
    left_by_itself: bool = False

    @property
    def controlword(self) -> int:
        """Return the controlword the gateway commands the drive now."""
        return self._controlword

    @controlword.setter
    def controlword(self, word: int) -> None:
        self._controlword = word
        self.left_by_itself = False  # a decision of the gateway's: what follows is asked

    def took_tpdo(self, values: Dict[int, int]) -> None:
        """Count a TPDO that brought feedback ``values`` (its lock held)."""
        self.tpdos += 1
        self.from_tpdo.update({index: (self.tpdos, value) for index, value in values.items()})

    def count(self, values: Dict[int, int]) -> None:
        """Count the statusword among ``values``, taken (its lock held)."""
        self.updates += cia402.STATUSWORD in values

    def newest(self, values: Dict[int, int], since: int, reread: bool) -> Dict[int, int]:
        """Return ``values`` read by SDO, asked after ``since`` TPDOs, as the newest known.

        An SDO answer is taken on an SDO thread, and may come after a TPDO sent later: what
        TPDOs brought since it was asked is newer and stays. A re-read takes it in (those
        TPDOs waited for the read). Its lock held.
        """
        newer = {index: value for index, (taken, value) in self.from_tpdo.items()
                 if taken > since}
        if reread:
            return {**values, **newer}
        return {index: value for index, value in values.items() if index not in newer}


def failed(status: DriveStatus, message: str, abort_code: int = 0) -> DriveResult:
    """Return the failed answer ``message`` for a drive whose status is ``status``."""
    return DriveResult(False, message, status, abort_code)


def shown(drive: DriveRecord) -> DriveStatus:
    """Return the status callers see (its lock held): UNKNOWN until the re-read is done."""
    if drive.ready == drive.read_wanted:
        return drive.status
    return replace(drive.status, state=cia402.UNKNOWN)


def updated(old: DriveStatus, values: Dict[int, int], stamp: float,
            emcy_code: int) -> DriveStatus:
    """Return the status of a drive that showed ``old`` once feedback ``values`` are in.

    ``stamp``: when they were received; ``emcy_code``: the error code of the drive's last EMCY.
    """
    statusword = values.get(cia402.STATUSWORD, old.statusword)
    state = cia402.state_of(statusword) if cia402.STATUSWORD in values else old.state
    # Built directly, not by replace(): this runs for every TPDO of every drive, and
    # replace() takes a third longer. By keyword: fields of one type must not swap.
    new = DriveStatus(node_id=old.node_id, state=state, statusword=statusword,
                      mode=values.get(cia402.MODE_DISPLAY, old.mode),
                      position=values.get(cia402.POSITION_ACTUAL, old.position),
                      velocity=values.get(cia402.VELOCITY_ACTUAL, old.velocity),
                      torque=values.get(cia402.TORQUE_ACTUAL, old.torque),
                      error_code=values.get(cia402.ERROR_CODE, old.error_code),
                      received=stamp, halted=old.halted, needs_enable=old.needs_enable,
                      changing_mode=old.changing_mode, supported_modes=old.supported_modes)
    if old.state == cia402.OPERATION_ENABLED and new.state != old.state:
        # Left it by itself: enable it afresh, whatever a set_mode under way had in mind.
        new = replace(new, needs_enable=True, changing_mode=False)
    if new.faulted and not old.faulted:
        # The EMCY the drive sent with its fault names the error until 0x603F is read.
        new = replace(new, needs_enable=True, changing_mode=False,
                      error_code=values.get(cia402.ERROR_CODE, emcy_code or old.error_code))
    return new
