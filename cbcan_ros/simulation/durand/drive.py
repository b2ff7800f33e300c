"""A simulated CiA 402 servo drive on durand, for testing the gateway's drive support.

:class:`DurandDrive` is a :class:`DurandDevice` (NMT, SDO, heartbeat, EMCY, PDOs) with the drive
objects of CiA 402. It follows the power state machine (``cia402_states``) on every write of
the controlword: by SDO within that write, by RPDO once every object of the frame is written.
One tick on the shared durand scheduler (every ``tick`` seconds), or an SDO request that
finds a tick overdue, moves the simulated axis in the mode of operation: profile position
(set-point handshake), profile velocity, homing, and the cyclic synchronous position,
velocity and torque modes. A consumer heartbeat (0x1016) watches the master: its loss
while the drive is enabled brings the reaction of 0x6007.

Units are whatever the master makes of them: positions in counts, velocities in counts/s,
accelerations in counts/s², torque in thousandths of rated torque.
"""

import enum
import functools
import logging
import math
import time
from typing import Callable, Optional

from .. import cia402_states as cia402
from ..cia402_states import State
from .device import DurandDevice
from .drive_objects import (
    ABORT_CONNECTION_OPTION,
    add_drive_objects,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    DISABLE_VOLTAGE,
    ERROR_CODE,
    FAULT_SIGNAL,
    HOME_OFFSET,
    HOMING_METHOD,
    MODE,
    MODE_DISPLAY,
    POSITION_ACTUAL,
    PROFILE_ACCELERATION,
    PROFILE_VELOCITY,
    QUICK_STOP,
    QUICK_STOP_DECELERATION,
    QUICK_STOP_OPTION,
    SIMULATED_FAULT,
    STATUSWORD,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)
from .heartbeat_consumer import HeartbeatConsumer
from .scheduler import shared_scheduler

LOGGER = logging.getLogger(__name__)

HEARTBEAT_ERROR = 0x8130  # CiA 301: life guard or heartbeat error

# Homing methods of CiA 402 the drive knows. 35 and 37 home where the axis stands; the others
# first drive to the simulated home switch, at position 0.
HOMING_METHODS = frozenset(range(1, 36)) | {37}
HOME_HERE = frozenset({35, 37})

# The made-up load in cyclic torque mode: velocity settles at once to this many counts/s per
# thousandth of rated torque.
VELOCITY_PER_TORQUE = 100

# Error register (0x1001) bit by an error code's first digit (CiA 301): current, voltage,
# temperature, communication. The generic bit goes with every error.
ERROR_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}
GENERIC_ERROR = 0x01

INT32_RANGE = 1 << 32


class Homing(enum.Enum):
    """Where a homing operation stands (statusword bits 10, 12 and 13 in homing mode)."""

    RUNNING = 'running'
    ATTAINED = 'attained'
    ERROR = 'error'


# 0x1018:1..4, as config/cia402_drive.eds gives them (a boot checks them against the file).
DRIVE_IDENTITY = (0x0, 0x402, 0x10000, 0x0)


class DurandDrive(DurandDevice):
    """One simulated CiA 402 servo drive on the bus, built on durand.

    ``modes``: the modes of operation it has (0x6502), among ``cia402_states.ALL_MODES``;
    ``tick``: seconds between two steps of motion. Other arguments are those of
    :class:`DurandDevice`. :attr:`state` stays the NMT state, as on every simulated device;
    :attr:`drive_state` is the CiA 402 state's name. :attr:`cyclic_target_reached` False
    makes it a drive that never sets statusword bit 10 in the cyclic modes, where CiA 402
    leaves that bit to the vendor; :attr:`halts_in_cyclic_modes` False one that ignores the
    halt bit there.
    """

    cyclic_target_reached = True
    # False: a drive that ignores the halt bit in the cyclic modes, as several vendors' do
    # (their manuals say bit 8 has no function there).
    halts_in_cyclic_modes = True
    # Seconds a drive confirms an SDO write of the controlword before it acts on it, as CiA
    # 402 allows (the statusword read right after still shows the state before).
    acts_after_confirming = 0.0

    def __init__(self, node_id: int, modes=cia402.ALL_MODES, tick: float = 0.01,
                 **device_options):
        unknown = set(modes) - set(cia402.ALL_MODES)
        if unknown:
            raise ValueError(f'modes of operation {sorted(unknown)} are not simulated')
        device_options.setdefault('identity', DRIVE_IDENTITY)
        super().__init__(node_id, **device_options)
        self.modes = frozenset(modes)
        self.tick = tick
        self._drive_state = State.NOT_READY_TO_SWITCH_ON
        self._controlword = 0
        self._in_rpdo = False
        self._rpdo_controlword: Optional[int] = None  # written by the RPDO being taken
        self._position = 0.0
        self._velocity = 0.0
        self._torque = 0
        self._last_tick = 0.0
        self._tick_timer = None
        self._pp_target: Optional[float] = None  # the set-point being travelled to
        self._pp_next: Optional[float] = None  # one buffered set-point
        self._pp_goal = 0.0  # the last set-point taken, what a relative one adds to
        self._set_point_acknowledged = False
        self._homing: Optional[Homing] = None
        self._master = HeartbeatConsumer(self._on_heartbeat_lost)

    @property
    def drive_state(self) -> str:
        """Return the name of the CiA 402 state (``'OPERATION_ENABLED'`` and the like)."""
        return self._drive_state.name

    position = property(lambda self: self._published(POSITION_ACTUAL),
                        doc='The position actual value (0x6064).')
    velocity = property(lambda self: self._published(VELOCITY_ACTUAL),
                        doc='The velocity actual value (0x606C).')
    torque = property(lambda self: self._published(TORQUE_ACTUAL),
                      doc='The torque actual value (0x6077).')
    statusword = property(lambda self: self._published(STATUSWORD),
                          doc='The statusword (0x6041).')

    def inject_fault(self, error_code: int) -> None:
        """Raise a fault: fault reaction, then FAULT; ``error_code`` in 0x603F and an EMCY."""
        self._started()
        with self._lock:
            self._fault(error_code)
            self._publish()

    def start(self) -> None:
        """Boot as every simulated device does, and start the motion tick."""
        super().start()
        with self._lock:
            if self._tick_timer is None:
                self._last_tick = time.monotonic()
                self._tick_timer = shared_scheduler().add(self.tick, self._on_tick)

    def stop(self) -> None:
        """Go silent, the tick and the heartbeat consumer with the rest."""
        if self._lock is not None:
            with self._lock:
                if self._tick_timer is not None:
                    shared_scheduler().cancel(self._tick_timer)
                    self._tick_timer = None
                self._master.stop()
        super().stop()

    def _published(self, index: int) -> int:
        node = self._started()
        with self._lock:
            return node.object_dictionary.read(index, 0)

    def _read(self, index: int) -> int:
        return self.node.object_dictionary.read(index, 0)

    def _build_dictionary(self, od) -> None:
        super()._build_dictionary(od)
        add_drive_objects(od, self.modes)
        self._on_write(od, CONTROLWORD, 0, self._on_controlword)
        self._on_write(od, MODE, 0, self._on_mode)
        self._on_write(od, SIMULATED_FAULT, 0, self._on_simulated_fault)
        for index in (TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE):
            # "Target reached" compares with them: a new one shows at once.
            self._on_write(od, index, 0, lambda value: self._publish())
        self._on_write(od, CONSUMER_HEARTBEAT, 1,
                       lambda entry: self._master.configure(self._network, entry))
        for rpdo in self.node.rpdo:
            # durand writes an RPDO's objects one by one, in mapping order, both as it arrives
            # and at a SYNC (durand 0.5.0 calls _write_data for either). A drive takes the
            # frame whole: a new set-point in the controlword takes the target position of
            # the same frame, mapped after it.
            rpdo._write_data = functools.partial(self._take_rpdo, rpdo._write_data)

    def _on_write(self, od, index: int, subindex: int, callback: Callable[[int], None]) -> None:
        od.update_callbacks[(index, subindex)].add(self._logged(index, subindex, callback))

    def _logged(self, index: int, subindex: int,
                callback: Callable[[int], None]) -> Callable[[int], None]:
        # durand swallows exceptions of update callbacks and of RPDO writes: a failing one
        # would go unseen.
        def logged(value: int) -> None:
            try:
                callback(value)
            except Exception:
                LOGGER.exception('simulated drive %d failed on 0x%04X:%d = %r',
                                 self.node_id, index, subindex, value)
        return logged

    def _take_rpdo(self, write: Callable[[bytes], None], data: bytes) -> None:
        self._in_rpdo, self._rpdo_controlword = True, None
        try:
            write(data)
        finally:
            self._in_rpdo = False
        if self._rpdo_controlword is not None:  # no confirmation to come first
            self._logged(CONTROLWORD, 0, self._act_on_controlword)(self._rpdo_controlword)

    def _boot(self, clear: range, durand_reset: Callable[[], None]) -> None:
        super()._boot(clear, durand_reset)
        if CONTROLWORD in clear:  # power-on or reset node, not reset communication
            self._controlword = 0
            self._position = 0.0
            self._stand_still()
            # Its self-test passes at once: NOT_READY_TO_SWITCH_ON moves on by itself.
            self._drive_state = State.SWITCH_ON_DISABLED
            self._publish()

    def _on_mode(self, mode: int) -> None:
        # The display still shows the mode before: a master that writes the same mode again
        # (an RPDO mapping 0x6060 does, every cycle) does not lose its set-points.
        if mode != self._read(MODE_DISPLAY):
            self._forget_set_points()
            self._publish()

    def _on_controlword(self, controlword: int) -> None:
        if self._in_rpdo:
            self._rpdo_controlword = controlword  # acted on once the whole frame is in
            return
        if self.acts_after_confirming:
            shared_scheduler().add(self.acts_after_confirming, self._logged(
                CONTROLWORD, 0, self._act_on_controlword), (controlword,))
            return
        self._act_on_controlword(controlword)

    def _act_on_controlword(self, controlword: int) -> None:
        previous, self._controlword = self._controlword, controlword
        state = self._drive_state
        if state is State.FAULT:
            if controlword & ~previous & cia402.FAULT_RESET:
                self._clear_fault()
        elif state is not State.FAULT_REACTION_ACTIVE:
            following = cia402.next_state(state, cia402.command_of(controlword),
                                          self._read(QUICK_STOP_OPTION))
            if following is not None:
                self._enter(following)
        if self._drive_state is State.OPERATION_ENABLED:
            self._on_mode_bits(previous, controlword)
        self._publish()

    def _enter(self, state: State) -> None:
        self._drive_state = state
        if state is State.OPERATION_ENABLED:
            self._forget_set_points()
        elif state is not State.QUICK_STOP_ACTIVE or self._read(QUICK_STOP_OPTION) == 0:
            self._stand_still()  # option 0 disables the drive function: nothing to ramp down

    def _stand_still(self) -> None:
        self._velocity = 0.0
        self._torque = 0

    def _forget_set_points(self) -> None:
        self._pp_target = self._pp_next = None
        self._pp_goal = self._position
        self._set_point_acknowledged = False
        self._homing = None

    def _on_mode_bits(self, previous: int, controlword: int) -> None:
        rising, falling = controlword & ~previous, previous & ~controlword
        mode = self._read(MODE)
        if mode == cia402.PROFILE_POSITION:
            if rising & cia402.NEW_SET_POINT:
                self._take_set_point(controlword)
            elif falling & cia402.NEW_SET_POINT:
                self._set_point_acknowledged = False
        elif mode == cia402.HOMING:
            if rising & cia402.NEW_SET_POINT:
                self._start_homing()
            elif falling & cia402.NEW_SET_POINT and self._homing is Homing.RUNNING:
                self._homing = None  # interrupted
                self._velocity = 0.0

    def _take_set_point(self, controlword: int) -> None:
        target = float(self._read(TARGET_POSITION))
        if controlword & cia402.RELATIVE:
            target += self._pp_goal
        if self._pp_target is None or controlword & cia402.CHANGE_SET_IMMEDIATELY:
            self._pp_target, self._pp_next = target, None
        elif self._pp_next is None:
            self._pp_next = target
        else:
            return  # the buffer is full: not acknowledged, the master must try again
        self._pp_goal = target
        self._set_point_acknowledged = True

    def _start_homing(self) -> None:
        method = self._read(HOMING_METHOD)
        if method not in HOMING_METHODS:
            self._homing = Homing.ERROR
        elif method in HOME_HERE:
            self._home()
        else:
            self._homing = Homing.RUNNING

    def _home(self) -> None:
        self._position = float(self._read(HOME_OFFSET))
        self._pp_goal = self._position
        self._homing = Homing.ATTAINED

    def _on_simulated_fault(self, error_code: int) -> None:
        if error_code and self._drive_state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self._fault(error_code)
            self._publish()

    def _fault(self, error_code: int) -> None:
        self._enter(State.FAULT_REACTION_ACTIVE)
        self.node.object_dictionary.write(ERROR_CODE, 0, error_code)
        register = GENERIC_ERROR | ERROR_REGISTER_BITS.get(error_code >> 12, 0)
        self.emergency(error_code, register)

    def _clear_fault(self) -> None:
        self._enter(State.SWITCH_ON_DISABLED)
        self.node.object_dictionary.write(ERROR_CODE, 0, 0)
        self.emergency(0)

    def _on_heartbeat_lost(self) -> None:
        if self._drive_state is not State.OPERATION_ENABLED:
            return
        option = self._read(ABORT_CONNECTION_OPTION)
        if option == FAULT_SIGNAL:
            self._fault(HEARTBEAT_ERROR)
        elif option == DISABLE_VOLTAGE:
            self._enter(State.SWITCH_ON_DISABLED)
        elif option == QUICK_STOP:
            self._enter(State.QUICK_STOP_ACTIVE)
        self._publish()

    def _on_tick(self) -> None:
        self._tick_timer = shared_scheduler().add(self.tick, self._on_tick)
        self._step()

    def _on_sdo_frame(self, durand_handler, cob_id: int, data: bytes) -> None:
        # A real drive's actual values are as new as its control cycle, whatever its bus does.
        # This one's tick runs on a thread a loaded machine can hold up for longer than a
        # master's standstill check (0.1 s): a read would then find the axis frozen in motion.
        if self._tick_timer is not None and time.monotonic() - self._last_tick >= self.tick:
            self._step()
        super()._on_sdo_frame(durand_handler, cob_id, data)

    def _step(self) -> None:
        """Move the axis on by the time since the last step, and publish what changed."""
        now = time.monotonic()
        elapsed, self._last_tick = now - self._last_tick, now
        state = self._drive_state
        if state is State.FAULT_REACTION_ACTIVE:
            self._drive_state = State.FAULT
        elif state is State.QUICK_STOP_ACTIVE:
            self._ramp(0.0, self._read(QUICK_STOP_DECELERATION), elapsed)
            if (self._velocity == 0.0
                    and self._read(QUICK_STOP_OPTION) not in cia402.STAY_IN_QUICK_STOP):
                self._drive_state = State.SWITCH_ON_DISABLED
        elif state is State.OPERATION_ENABLED and elapsed > 0:
            self._move(elapsed)
        self._publish()

    @property
    def _halted(self) -> bool:
        return (self._drive_state is State.OPERATION_ENABLED
                and bool(self._controlword & cia402.HALT)
                and (self.halts_in_cyclic_modes or self._read(MODE) not in cia402.CYCLIC_MODES))

    def _move(self, elapsed: float) -> None:
        mode = self._read(MODE)
        self._torque = 0
        if self._halted:
            self._ramp(0.0, self._read(PROFILE_ACCELERATION), elapsed)
        elif mode == cia402.PROFILE_VELOCITY:
            self._ramp(self._read(TARGET_VELOCITY), self._read(PROFILE_ACCELERATION), elapsed)
        elif mode == cia402.CYCLIC_VELOCITY:
            self._ramp(self._read(TARGET_VELOCITY), 0, elapsed)
        elif mode in cia402.TORQUE_MODES:
            self._torque = self._read(TARGET_TORQUE)
            self._ramp(self._torque * VELOCITY_PER_TORQUE, 0, elapsed)
        elif mode == cia402.CYCLIC_POSITION:
            target = float(self._read(TARGET_POSITION))
            # Over one control cycle at the least: a tick right after an SDO frame's step
            # (a loaded machine) took a step of 250 counts as millions of counts/s, and a
            # halt then braked from that speed for minutes.
            self._velocity = (target - self._position) / max(elapsed, self.tick)
            self._position = target
        elif mode == cia402.PROFILE_POSITION and self._pp_target is not None:
            if self._travel(self._pp_target, elapsed):
                self._pp_target, self._pp_next = self._pp_next, None
        elif mode == cia402.HOMING and self._homing is Homing.RUNNING:
            if self._travel(0.0, elapsed):
                self._home()
        else:
            self._velocity = 0.0

    def _ramp(self, velocity: float, acceleration: float, elapsed: float) -> None:
        """Change the velocity toward ``velocity`` at ``acceleration`` (0: at once), and move."""
        before = self._velocity
        step = acceleration * elapsed if acceleration else math.inf
        self._velocity = before + max(-step, min(step, velocity - before))
        self._position += (before + self._velocity) / 2 * elapsed

    def _travel(self, goal: float, elapsed: float) -> bool:
        """Move toward ``goal`` at the profile velocity; return whether it is reached."""
        speed = self._read(PROFILE_VELOCITY)
        distance = goal - self._position
        if abs(distance) <= speed * elapsed:
            self._position, self._velocity = goal, 0.0
            return True
        self._velocity = math.copysign(speed, distance)
        self._position += self._velocity * elapsed
        return False

    def _publish(self) -> None:
        """Write what changed into the objects the master reads (and TPDOs carry)."""
        od = self.node.object_dictionary
        values = {
            STATUSWORD: self._statusword(),
            MODE_DISPLAY: self._read(MODE),
            POSITION_ACTUAL: _wrap_int32(round(self._position)),
            VELOCITY_ACTUAL: _clamp_int32(round(self._velocity)),
            TORQUE_ACTUAL: self._torque,
        }
        for index, value in values.items():
            if od.read(index, 0) != value:
                od.write(index, 0, value)

    def _statusword(self) -> int:
        state = self._drive_state
        word = state.value | cia402.REMOTE
        if state in cia402.POWERED:
            word |= cia402.VOLTAGE_ENABLED
        if state is State.QUICK_STOP_ACTIVE and self._velocity == 0.0:
            word |= cia402.TARGET_REACHED
        if state is not State.OPERATION_ENABLED:
            return word
        reached, mode_bits = self._mode_status()
        if self._halted:
            word |= cia402.HALT_ACTIVE
            reached = self._velocity == 0.0
        if self._read(MODE) in cia402.CYCLIC_MODES and not self.cyclic_target_reached:
            reached = False
        return word | mode_bits | (cia402.TARGET_REACHED if reached else 0)

    def _mode_status(self):
        """Return whether the target is reached, and statusword bits 12 and 13, in the mode."""
        mode = self._read(MODE)
        following = 0 if self._halted else cia402.MODE_BIT_12
        if mode == cia402.PROFILE_POSITION:
            return (self._pp_target is None,
                    cia402.MODE_BIT_12 if self._set_point_acknowledged else 0)
        if mode == cia402.PROFILE_VELOCITY:
            return (self._velocity == self._read(TARGET_VELOCITY),
                    cia402.MODE_BIT_12 if self._velocity == 0.0 else 0)
        if mode == cia402.HOMING:
            return (self._homing is not Homing.RUNNING,
                    {Homing.ATTAINED: cia402.MODE_BIT_12,
                     Homing.ERROR: cia402.MODE_BIT_13}.get(self._homing, 0))
        if mode == cia402.CYCLIC_POSITION:
            return round(self._position) == self._read(TARGET_POSITION), following
        if mode == cia402.CYCLIC_VELOCITY:
            return self._velocity == self._read(TARGET_VELOCITY), following
        if mode == cia402.CYCLIC_TORQUE:
            return self._torque == self._read(TARGET_TORQUE), following
        if mode == cia402.PROFILE_TORQUE:
            return self._torque == self._read(TARGET_TORQUE), 0
        return False, 0


def _wrap_int32(value: int) -> int:
    """Return ``value`` as a 32-bit position counter shows it: wrapped around."""
    return (value + INT32_RANGE // 2) % INT32_RANGE - INT32_RANGE // 2


def _clamp_int32(value: int) -> int:
    return max(-INT32_RANGE // 2, min(INT32_RANGE // 2 - 1, value))
