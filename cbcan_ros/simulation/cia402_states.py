"""The CiA 402 power state machine of a simulated drive: states, commands, transitions, bits.

Pure logic, no bus: :mod:`durand.drive` feeds it every controlword written and shows its state
in the statusword. Masks and values are those of CiA 402 (IEC 61800-7-201).
"""

import enum
from typing import Optional


class State(enum.Enum):
    """A state of the power state machine; the value is its statusword bits 0..3, 5 and 6."""

    NOT_READY_TO_SWITCH_ON = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08


class Command(enum.Enum):
    """A device control command, as coded in controlword bits 0..3."""

    DISABLE_VOLTAGE = 'disable voltage'
    QUICK_STOP = 'quick stop'
    SHUTDOWN = 'shutdown'
    SWITCH_ON = 'switch on'  # also "disable operation" from OPERATION_ENABLED
    ENABLE_OPERATION = 'enable operation'


# Controlword bits.
ENABLE_VOLTAGE = 1 << 1
QUICK_STOP_OFF = 1 << 2  # 0 commands a quick stop
SWITCH_ON_BIT = 1 << 0
ENABLE_OPERATION_BIT = 1 << 3
NEW_SET_POINT = 1 << 4  # also homing operation start
CHANGE_SET_IMMEDIATELY = 1 << 5
RELATIVE = 1 << 6
FAULT_RESET = 1 << 7
HALT = 1 << 8

# Statusword bits besides the state's.
VOLTAGE_ENABLED = 1 << 4
HALT_ACTIVE = 1 << 8
REMOTE = 1 << 9
TARGET_REACHED = 1 << 10
MODE_BIT_12 = 1 << 12  # PP set-point acknowledge, homing attained, PV speed 0, CSx following
MODE_BIT_13 = 1 << 13  # homing error

# Modes of operation (0x6060); a drive lists the ones it has in 0x6502, bit (mode - 1).
PROFILE_POSITION = 1
PROFILE_VELOCITY = 3
HOMING = 6
CYCLIC_POSITION = 8
CYCLIC_VELOCITY = 9
CYCLIC_TORQUE = 10
PROFILE_TORQUE = 4
ALL_MODES = (PROFILE_POSITION, PROFILE_VELOCITY, PROFILE_TORQUE, HOMING, CYCLIC_POSITION,
             CYCLIC_VELOCITY, CYCLIC_TORQUE)
TORQUE_MODES = frozenset({PROFILE_TORQUE, CYCLIC_TORQUE})
CYCLIC_MODES = frozenset({CYCLIC_POSITION, CYCLIC_VELOCITY, CYCLIC_TORQUE})

# States with the power stage on: statusword bit 4.
POWERED = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                     State.QUICK_STOP_ACTIVE})

_TRANSITIONS = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 2
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): State.SWITCHED_ON,  # 3
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 3 + 4
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 7
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 7
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 4
    (State.SWITCHED_ON, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 6
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 10
    (State.SWITCHED_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 10
    (State.OPERATION_ENABLED, Command.SWITCH_ON): State.SWITCHED_ON,  # 5
    (State.OPERATION_ENABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 8
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 9
    (State.OPERATION_ENABLED, Command.QUICK_STOP): State.QUICK_STOP_ACTIVE,  # 11
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 12
}

# Quick stop option codes (0x605A) after which the drive stays in QUICK_STOP_ACTIVE, and may
# return to OPERATION_ENABLED (transition 16); with the others it ends in SWITCH_ON_DISABLED.
STAY_IN_QUICK_STOP = range(5, 9)


def command_of(controlword: int) -> Command:
    """Return the command that controlword bits 0..3 give (bit 7 is the fault reset's)."""
    if not controlword & ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & QUICK_STOP_OFF:
        return Command.QUICK_STOP
    if not controlword & SWITCH_ON_BIT:
        return Command.SHUTDOWN
    if not controlword & ENABLE_OPERATION_BIT:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


def next_state(state: State, command: Command, quick_stop_option: int) -> Optional[State]:
    """Return the state ``command`` leads to from ``state``, or None when it is no transition."""
    if (state, command) == (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION):
        return State.OPERATION_ENABLED if quick_stop_option in STAY_IN_QUICK_STOP else None
    return _TRANSITIONS.get((state, command))


def supported_modes_bits(modes) -> int:
    """Return 0x6502's value for the modes of operation ``modes``."""
    return sum(1 << (mode - 1) for mode in set(modes))
