"""The PDO mapping a simulated CiA 402 drive has out of the box, as real drives commonly ship.

The gateway reads it over SDO like any device's mapping (``pdo.nodes``), and its drive support
can move the drive with it without configuring anything: the controlword, target position and
mode of operation in RPDO 1, target velocity and torque in RPDO 2; the statusword with the mode
shown and the torque in TPDO 1, position and velocity in TPDO 2.
"""

from typing import Tuple

from .durand_drive_objects import (
    CONTROLWORD,
    MODE,
    MODE_DISPLAY,
    POSITION_ACTUAL,
    STATUSWORD,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)
from .durand_pdos import PdoConfig

# Transmission types (CiA 301). durand sends a TPDO of type 255 on every write of a mapped
# object (the drive writes its objects only when they change) and one of type 254 only from its
# event timer (durand_pdos); both apply an RPDO as it arrives.
EVENT_DRIVEN = 255
TIMER_DRIVEN = 254
SYNCHRONOUS = 1  # every SYNC: a TPDO answers each SYNC, an RPDO is applied at the next SYNC

# Event timers (ms): feedback flows without SYNC, and the gateway can tell a silent drive.
STATUS_EVENT_TIMER = 20
MOTION_EVENT_TIMER = 10

STATUS = ((STATUSWORD, 0), (MODE_DISPLAY, 0), (TORQUE_ACTUAL, 0))  # 16 + 8 + 16 bits
MOTION = ((POSITION_ACTUAL, 0), (VELOCITY_ACTUAL, 0))  # 32 + 32 bits
COMMAND = ((CONTROLWORD, 0), (TARGET_POSITION, 0), (MODE, 0))  # 16 + 32 + 8 bits
SET_POINTS = ((TARGET_VELOCITY, 0), (TARGET_TORQUE, 0))  # 32 + 16 bits


def default_drive_pdos(transmission_type: int = 0) -> Tuple[PdoConfig, ...]:
    """Return the PDOs of a simulated drive: TPDO 1 and 2, RPDO 1 and 2; 3 and 4 disabled.

    By default the statusword goes out on every change and every 20 ms, position and velocity
    every 10 ms (every tick of motion would change them: sent on change they would flood the
    bus), and RPDOs are applied as they arrive. ``transmission_type`` 1..240 makes all four
    synchronous instead, without event timers.
    """
    # PDOs 3 and 4 are off: durand has them on, with nothing mapped.
    unused = tuple(PdoConfig(kind, number, (), enabled=False)
                   for kind in ('tpdo', 'rpdo') for number in (3, 4))
    if transmission_type:
        return tuple(PdoConfig(kind, number, mapping, transmission_type)
                     for kind, number, mapping in (('tpdo', 1, STATUS), ('tpdo', 2, MOTION),
                                                   ('rpdo', 1, COMMAND),
                                                   ('rpdo', 2, SET_POINTS))) + unused
    return (
        PdoConfig('tpdo', 1, STATUS, EVENT_DRIVEN, event_timer=STATUS_EVENT_TIMER),
        PdoConfig('tpdo', 2, MOTION, TIMER_DRIVEN, event_timer=MOTION_EVENT_TIMER),
        PdoConfig('rpdo', 1, COMMAND, EVENT_DRIVEN),
        PdoConfig('rpdo', 2, SET_POINTS, EVENT_DRIVEN),
    ) + unused
