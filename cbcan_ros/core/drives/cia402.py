"""CiA 402 (IEC 61800-7-201) as the master sees a drive: objects, states, controlwords, errors.

Pure vocabulary, no bus: :mod:`drive` reads a drive's state from each statusword with
:func:`state_of`, finds the controlword that takes it one step nearer a wanted state with
:func:`step_towards`, and names an error code with :func:`error_meaning`. Object semantics
follow the profile (python canopen's ``BaseNode402`` reads the same way).
"""

from typing import Optional

from canopen.emcy import EmcyError

# Objects of the profile the gateway uses.
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODE = 0x6060
MODE_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
TORQUE_ACTUAL = 0x6077
POSITION_WINDOW = 0x6067
VELOCITY_THRESHOLD = 0x606F  # the velocity regarded as 0 (CiA 402, profile velocity)
SOFTWARE_POSITION_LIMIT = 0x607D  # record: 1 minimum, 2 maximum (INTEGER32)
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
HOMING_METHOD = 0x6098
PROFILE_VELOCITY_OBJECT = 0x6081  # not PROFILE_VELOCITY, the mode
TARGET_VELOCITY = 0x60FF
SUPPORTED_MODES = 0x6502
CONSUMER_HEARTBEAT = 0x1016

# How each object is coded (struct format, little-endian), for SDO access and PDO decoding.
FORMATS = {
    ERROR_CODE: '<H', CONTROLWORD: '<H', STATUSWORD: '<H', MODE: '<b', MODE_DISPLAY: '<b',
    POSITION_ACTUAL: '<i', VELOCITY_ACTUAL: '<i', TARGET_TORQUE: '<h', TORQUE_ACTUAL: '<h',
    TARGET_POSITION: '<i', PROFILE_VELOCITY_OBJECT: '<I', TARGET_VELOCITY: '<i',
    SUPPORTED_MODES: '<I', CONSUMER_HEARTBEAT: '<I', POSITION_WINDOW: '<I',
    VELOCITY_THRESHOLD: '<H',
    HOME_OFFSET: '<i', HOMING_METHOD: '<b', ABORT_CONNECTION_OPTION: '<h',
    SOFTWARE_POSITION_LIMIT: '<i',  # each of its two sub-entries
}

# States: (statusword mask, value), checked in this order.
NOT_READY_TO_SWITCH_ON = 'NOT_READY_TO_SWITCH_ON'
SWITCH_ON_DISABLED = 'SWITCH_ON_DISABLED'
READY_TO_SWITCH_ON = 'READY_TO_SWITCH_ON'
SWITCHED_ON = 'SWITCHED_ON'
OPERATION_ENABLED = 'OPERATION_ENABLED'
QUICK_STOP_ACTIVE = 'QUICK_STOP_ACTIVE'
FAULT_REACTION_ACTIVE = 'FAULT_REACTION_ACTIVE'
FAULT = 'FAULT'
UNKNOWN = 'UNKNOWN'  # not heard (yet, or any more): no statusword to read a state from
STATES = (
    (NOT_READY_TO_SWITCH_ON, 0x4F, 0x00), (SWITCH_ON_DISABLED, 0x4F, 0x40),
    (READY_TO_SWITCH_ON, 0x6F, 0x21), (SWITCHED_ON, 0x6F, 0x23),
    (OPERATION_ENABLED, 0x6F, 0x27), (QUICK_STOP_ACTIVE, 0x6F, 0x07),
    (FAULT_REACTION_ACTIVE, 0x4F, 0x0F), (FAULT, 0x4F, 0x08),
)
FAULTED = frozenset({FAULT, FAULT_REACTION_ACTIVE})
# States in which the power stage may turn the motor: what shutdown and safety stops act on.
POWERED = frozenset({READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE})

# Controlword commands (bits 0..3) and bits.
DISABLE_VOLTAGE = 0x00
QUICK_STOP = 0x02
SHUTDOWN = 0x06
SWITCH_ON = 0x07
ENABLE_OPERATION = 0x0F
COMMAND_BITS = 0x8F  # bits 0..3 and 7
# The command that keeps a drive in each state it does not leave by itself.
KEEPS = {SWITCH_ON_DISABLED: DISABLE_VOLTAGE, READY_TO_SWITCH_ON: SHUTDOWN,
         SWITCHED_ON: SWITCH_ON, OPERATION_ENABLED: ENABLE_OPERATION,
         QUICK_STOP_ACTIVE: QUICK_STOP}
NEW_SET_POINT = 1 << 4  # also homing operation start
CHANGE_SET_IMMEDIATELY = 1 << 5
RELATIVE = 1 << 6
FAULT_RESET = 1 << 7
HALT = 1 << 8
MODE_BITS = NEW_SET_POINT | CHANGE_SET_IMMEDIATELY | RELATIVE

# Statusword bits besides the state's.
TARGET_REACHED = 1 << 10
MODE_BIT_12 = 1 << 12  # PP set-point acknowledge, homing attained
MODE_BIT_13 = 1 << 13  # homing error, following error

# Modes of operation (0x6060 / 0x6061); 0x6502 has bit (mode - 1) for each mode a drive has.
PROFILE_POSITION = 1
PROFILE_VELOCITY = 3
PROFILE_TORQUE = 4
HOMING = 6
CYCLIC_POSITION = 8
CYCLIC_VELOCITY = 9
CYCLIC_TORQUE = 10
MODE_NAMES = {
    PROFILE_POSITION: 'profile position (PP)', PROFILE_VELOCITY: 'profile velocity (PV)',
    PROFILE_TORQUE: 'profile torque (PT)', HOMING: 'homing',
    CYCLIC_POSITION: 'cyclic synchronous position (CSP)',
    CYCLIC_VELOCITY: 'cyclic synchronous velocity (CSV)',
    CYCLIC_TORQUE: 'cyclic synchronous torque (CST)',
}
# The object a target sets in each mode, and what holds the axis where it is.
TARGET_OF_MODE = {
    PROFILE_POSITION: TARGET_POSITION, CYCLIC_POSITION: TARGET_POSITION,
    PROFILE_VELOCITY: TARGET_VELOCITY, CYCLIC_VELOCITY: TARGET_VELOCITY,
    PROFILE_TORQUE: TARGET_TORQUE, CYCLIC_TORQUE: TARGET_TORQUE,
}
# Modes whose target is streamed: the command timeout halts them when it stops coming.
STREAMING_MODES = frozenset({PROFILE_VELOCITY, PROFILE_TORQUE, CYCLIC_POSITION,
                             CYCLIC_VELOCITY, CYCLIC_TORQUE})
# Modes where a halt also sets the target that stops the axis (position: where it stands):
# several vendors ignore the halt bit in the cyclic modes and PT (their manuals: "no
# function" there); in PV the velocity left in force would run again at a resume, the
# velocity of a publisher that is gone.
HALT_BY_TARGET = {CYCLIC_POSITION: TARGET_POSITION, CYCLIC_VELOCITY: TARGET_VELOCITY,
                  CYCLIC_TORQUE: TARGET_TORQUE, PROFILE_TORQUE: TARGET_TORQUE,
                  PROFILE_VELOCITY: TARGET_VELOCITY}

# Error codes (0x603F, EMCY) of CiA 402-2 and CiA 301, the ones drives commonly report; other
# codes are named by their CiA 301 class.
ERROR_MEANINGS = {
    0x0000: 'no error',
    0x1000: 'generic error',
    0x2110: 'short circuit or earth leakage (input)',
    0x2220: 'continuous over-current (device internal)',
    0x2230: 'short circuit or earth leakage (device internal)',
    0x2310: 'continuous over-current',
    0x2311: 'continuous over-current No. 1',
    0x2320: 'short circuit or earth leakage (motor side)',
    0x2330: 'earth leakage',
    0x2340: 'short circuit',
    0x3110: 'mains over-voltage',
    0x3120: 'mains under-voltage',
    0x3130: 'phase failure',
    0x3210: 'DC link over-voltage',
    0x3220: 'DC link under-voltage',
    0x4210: 'excess temperature (device)',
    0x4310: 'excess temperature (drive)',
    0x4410: 'excess temperature (supply)',
    0x5112: 'supply voltage low',
    0x5113: 'logic supply voltage low',
    0x5210: 'measurement circuit',
    0x5400: 'power section',
    0x5441: 'drive disabled by a limit (e.g. safe torque off)',
    0x6010: 'software reset (watchdog)',
    0x6320: 'parameter error',
    0x7110: 'brake chopper',
    0x7120: 'motor',
    0x7121: 'motor blocked',
    0x7300: 'sensor',
    0x7305: 'incremental sensor 1 fault',
    0x7310: 'speed sensor (tachometer)',
    0x7320: 'position sensor',
    0x8110: 'CAN overrun (objects lost)',
    0x8120: 'CAN in error passive mode',
    0x8130: 'life guard or heartbeat error',
    0x8140: 'recovered from bus off',
    0x8611: 'following error',
    0x8612: 'reference limit',
    0xFF00: 'device specific',
}


def state_of(statusword: int) -> str:
    """Return the name of the state a statusword shows."""
    for name, mask, value in STATES:
        if statusword & mask == value:
            return name
    return UNKNOWN  # 0x0F without bit 3 and the like: no state of the profile


def stops(controlword: int) -> bool:
    """Return whether ``controlword`` stops the axis: halt, quick stop or disable voltage."""
    return bool(controlword & HALT) or switches_off(controlword)


def switches_off(controlword: int) -> bool:
    """Return whether ``controlword`` is quick stop or disable voltage: it enables nothing.

    The commands with bit 1 or bit 2 clear (CiA 402). A halt (bit 8) with enable operation
    still enables: a drive in QUICK_STOP_ACTIVE takes it as transition 16.
    """
    return controlword & 0x06 != 0x06


def error_meaning(code: int) -> str:
    """Return what an error code of 0x603F or an EMCY means, e.g. 'DC link over-voltage'."""
    if code in ERROR_MEANINGS:
        return ERROR_MEANINGS[code]
    described = EmcyError(code, 0, b'', 0).get_desc()
    return f'{described.lower()} error' if described else 'unknown error code'


def mode_name(mode: int) -> str:
    """Return a mode of operation as people know it, e.g. 'cyclic synchronous velocity (CSV)'."""
    return MODE_NAMES.get(mode, f'mode {mode}')


def supports(supported_modes: int, mode: int) -> bool:
    """Return whether 0x6502's value ``supported_modes`` lists ``mode``."""
    return 1 <= mode <= 32 and bool(supported_modes >> (mode - 1) & 1)


def step_towards(state: str, wanted: str) -> Optional[int]:
    """Return the controlword command (bits 0..3) that brings ``state`` nearer ``wanted``.

    None when there is nothing to send: already there, a state the drive leaves by itself
    (NOT_READY_TO_SWITCH_ON, FAULT_REACTION_ACTIVE), or FAULT, which only a fault reset
    leaves. ``wanted`` is OPERATION_ENABLED (the enable path, one transition a step, as every
    drive takes it), SWITCH_ON_DISABLED (disable voltage) or QUICK_STOP_ACTIVE.
    """
    if state == wanted or state in FAULTED or state in (NOT_READY_TO_SWITCH_ON, UNKNOWN):
        return None
    if wanted == SWITCH_ON_DISABLED:
        return None if state == SWITCH_ON_DISABLED else DISABLE_VOLTAGE
    if wanted == QUICK_STOP_ACTIVE:
        # From OPERATION_ENABLED a quick stop ramps down; elsewhere the motor is not driven,
        # and the same command switches the power stage off.
        return None if state == SWITCH_ON_DISABLED else QUICK_STOP
    return {SWITCH_ON_DISABLED: SHUTDOWN, READY_TO_SWITCH_ON: SWITCH_ON,
            SWITCHED_ON: ENABLE_OPERATION, QUICK_STOP_ACTIVE: DISABLE_VOLTAGE}.get(state)
