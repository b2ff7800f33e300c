"""The object dictionary of the simulated CiA 402 drive (``drive``): indexes, defaults.

Added to a durand node next to the generic device's objects (``dictionary``), with the
range checks a drive makes before it takes a value (SDO abort 0x06090030 otherwise).
"""

from typing import Iterable

from durand.datatypes import DatatypeEnum as DT
from durand.object_dictionary import Array, ObjectDictionary, Record, Variable
from durand.services.sdo.server import SDODomainAbort

from .. import cia402_states as cia402

DEVICE_NAME = 0x1008
CONSUMER_HEARTBEAT = 0x1016
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODE = 0x6060
MODE_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
POSITION_WINDOW = 0x6067
SOFTWARE_POSITION_LIMIT = 0x607D
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
PROFILE_VELOCITY = 0x6081
PROFILE_ACCELERATION = 0x6083
QUICK_STOP_DECELERATION = 0x6085
HOMING_METHOD = 0x6098
TARGET_VELOCITY = 0x60FF
SUPPORTED_MODES = 0x6502
# Not of CiA 402: writing an error code here makes the simulated drive fault with it, as a
# real drive does on an over-current, so a fault can be tried from outside its process.
SIMULATED_FAULT = 0x2FFF
INTERPOLATION_TIME_PERIOD = 0x60C2

ABORT_VALUE_RANGE = 0x06090030

# Abort connection option codes (0x6007), as CiA 402 numbers them.
NO_ACTION, FAULT_SIGNAL, DISABLE_VOLTAGE, QUICK_STOP = range(4)

# Quick stop option code (0x605A) 2: ramp down at 0x6085, then SWITCH_ON_DISABLED.
QUICK_STOP_RAMP_THEN_DISABLE = 2

# (index, datatype, access, default, name); 0x6502 and 0x1016 are added apart.
OBJECTS = (
    (ABORT_CONNECTION_OPTION, DT.INTEGER16, 'rw', QUICK_STOP, 'Abort connection option code'),
    (ERROR_CODE, DT.UNSIGNED16, 'ro', 0, 'Error code'),
    (CONTROLWORD, DT.UNSIGNED16, 'rw', 0, 'Controlword'),
    (STATUSWORD, DT.UNSIGNED16, 'ro', 0, 'Statusword'),
    (QUICK_STOP_OPTION, DT.INTEGER16, 'rw', QUICK_STOP_RAMP_THEN_DISABLE,
     'Quick stop option code'),
    (MODE, DT.INTEGER8, 'rw', 0, 'Modes of operation'),
    (MODE_DISPLAY, DT.INTEGER8, 'ro', 0, 'Modes of operation display'),
    (POSITION_ACTUAL, DT.INTEGER32, 'ro', 0, 'Position actual value'),
    (VELOCITY_ACTUAL, DT.INTEGER32, 'ro', 0, 'Velocity actual value'),
    (POSITION_WINDOW, DT.UNSIGNED32, 'rw', 10, 'Position window'),
    (TARGET_TORQUE, DT.INTEGER16, 'rw', 0, 'Target torque'),
    (MAX_TORQUE, DT.UNSIGNED16, 'rw', 1000, 'Max torque'),
    (TORQUE_ACTUAL, DT.INTEGER16, 'ro', 0, 'Torque actual value'),
    (TARGET_POSITION, DT.INTEGER32, 'rw', 0, 'Target position'),
    (HOME_OFFSET, DT.INTEGER32, 'rw', 0, 'Home offset'),
    (PROFILE_VELOCITY, DT.UNSIGNED32, 'rw', 10_000, 'Profile velocity'),
    (PROFILE_ACCELERATION, DT.UNSIGNED32, 'rw', 100_000, 'Profile acceleration'),
    (QUICK_STOP_DECELERATION, DT.UNSIGNED32, 'rw', 500_000, 'Quick stop deceleration'),
    (HOMING_METHOD, DT.INTEGER8, 'rw', 35, 'Homing method'),
    (TARGET_VELOCITY, DT.INTEGER32, 'rw', 0, 'Target velocity'),
)

# Option codes the drive knows; another value is refused as out of range.
OPTION_RANGES = {QUICK_STOP_OPTION: range(0, 9), ABORT_CONNECTION_OPTION: range(0, 4)}


def add_drive_objects(od: ObjectDictionary, modes: Iterable[int]) -> None:
    """Put the drive's objects into ``od``, for a drive with the modes of operation ``modes``.

    A mode of operation outside ``modes`` (0, no mode, aside) is refused, as are unknown
    option codes.
    """
    modes = frozenset(modes)
    od[DEVICE_NAME] = Variable(DT.VISIBLE_STRING, 'const', b'cbcan simulated CiA 402 drive',
                               name='Manufacturer device name')
    for index, datatype, access, default, name in OBJECTS:
        od[index] = Variable(datatype, access, default, name=name)
    od[SIMULATED_FAULT] = Variable(DT.UNSIGNED16, 'rw', 0, name='Simulated fault')
    od[SUPPORTED_MODES] = Variable(DT.UNSIGNED32, 'ro', cia402.supported_modes_bits(modes),
                                   name='Supported drive modes')
    limits = Record(name='Software position limit')  # none, as many drives ship
    limits[1] = Variable(DT.INTEGER32, 'rw', -(1 << 31), name='Min position limit')
    limits[2] = Variable(DT.INTEGER32, 'rw', (1 << 31) - 1, name='Max position limit')
    od[SOFTWARE_POSITION_LIMIT] = limits
    # The cycle time of the cyclic modes, as drives with CSP have it: value x 10^index s.
    period = Record(name='Interpolation time period')
    period[1] = Variable(DT.UNSIGNED8, 'rw', 1, name='Interpolation time period value')
    period[2] = Variable(DT.INTEGER8, 'rw', -3, name='Interpolation time index')
    od[INTERPOLATION_TIME_PERIOD] = period
    od[CONSUMER_HEARTBEAT] = Array(Variable(DT.UNSIGNED32, 'rw', 0,
                                            name='Consumer heartbeat time'),
                                   length=1, name='Consumer heartbeat time')
    od.validate_callbacks[(MODE, 0)].add(
        lambda mode: _check_range(MODE, mode, modes | {0}))
    for index, allowed in OPTION_RANGES.items():
        od.validate_callbacks[(index, 0)].add(
            lambda value, index=index, allowed=allowed: _check_range(index, value, allowed))


def _check_range(index: int, value: int, allowed) -> None:
    if value not in allowed:
        raise SDODomainAbort(ABORT_VALUE_RANGE, (index, 0))
