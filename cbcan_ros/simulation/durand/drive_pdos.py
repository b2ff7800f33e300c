"""The PDO mappings a simulated CiA 402 drive can have out of the box: its layouts.

The gateway reads them over SDO like any device's mapping (``pdo.nodes``), and its drive
support must move the drive with each without configuring anything (named in
``simulated_drives.LAYOUTS``):

- ``combined`` (``make run``'s drive): the controlword, target position and mode of operation
  in RPDO 1, target velocity and torque in RPDO 2; the statusword with the mode shown and the
  torque in TPDO 1, position and velocity in TPDO 2.
- ``vendor``: the CiA 402 defaults of vendor EDS files (Maxon EPOS2, Faulhaber MC,
  Wittenstein simco): the controlword in every RPDO, alone in RPDO 1, with the mode in
  RPDO 2, the target position in RPDO 3, the target velocity in RPDO 4; the statusword in
  every TPDO, with the mode shown in TPDO 2, the position in TPDO 3, the velocity in TPDO 4.
- ``ros2_canopen``: the layout of ros2_canopen's CiA 402 examples
  (``canopen_tests/config/cia402/bus.yml``): controlword and mode in RPDO 1, target position
  and velocity in RPDO 2; statusword and mode shown in TPDO 1, position and velocity in
  TPDO 2, both TPDOs synchronous (sent only while a master produces SYNC).
- ``sdo_only``: no PDO enabled; the drive is run by SDO alone.
"""

from typing import Tuple

from ..simulated_drives import LAYOUTS
from .drive_objects import (
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
from .pdos import PdoConfig

# Transmission types (CiA 301). durand sends a TPDO of type 255 on every write of a mapped
# object (the drive writes its objects only when they change) and one of type 254 only from its
# event timer (pdos); both apply an RPDO as it arrives.
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
    unused = _unused((3, 4))  # durand has them on, with nothing mapped
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


def vendor_drive_pdos() -> Tuple[PdoConfig, ...]:
    """Return the CiA 402 vendor default layout: the controlword in every RPDO."""
    controlword, statusword = (CONTROLWORD, 0), (STATUSWORD, 0)
    rpdos = ((controlword,), (controlword, (MODE, 0)), (controlword, (TARGET_POSITION, 0)),
             (controlword, (TARGET_VELOCITY, 0)))
    tpdos = ((statusword,), (statusword, (MODE_DISPLAY, 0)),
             (statusword, (POSITION_ACTUAL, 0)), (statusword, (VELOCITY_ACTUAL, 0)))
    return tuple(PdoConfig('rpdo', number, mapping, EVENT_DRIVEN)
                 for number, mapping in enumerate(rpdos, 1)) + tuple(
        PdoConfig('tpdo', number, mapping, EVENT_DRIVEN, event_timer=STATUS_EVENT_TIMER)
        if number <= 2 else
        PdoConfig('tpdo', number, mapping, TIMER_DRIVEN, event_timer=MOTION_EVENT_TIMER)
        for number, mapping in enumerate(tpdos, 1))


def ros2_canopen_drive_pdos() -> Tuple[PdoConfig, ...]:
    """Return the layout of ros2_canopen's CiA 402 examples: synchronous TPDOs."""
    return (
        PdoConfig('tpdo', 1, ((STATUSWORD, 0), (MODE_DISPLAY, 0)), SYNCHRONOUS),
        PdoConfig('tpdo', 2, MOTION, SYNCHRONOUS),
        PdoConfig('rpdo', 1, ((CONTROLWORD, 0), (MODE, 0)), EVENT_DRIVEN),
        PdoConfig('rpdo', 2, ((TARGET_POSITION, 0), (TARGET_VELOCITY, 0)), EVENT_DRIVEN),
    ) + _unused((3, 4))


def sdo_only_drive_pdos() -> Tuple[PdoConfig, ...]:
    """Return a layout with every PDO disabled: the drive is run by SDO."""
    return _unused((1, 2, 3, 4))


def _unused(numbers) -> Tuple[PdoConfig, ...]:
    return tuple(PdoConfig(kind, number, (), enabled=False)
                 for kind in ('tpdo', 'rpdo') for number in numbers)



def drive_pdos(layout: str) -> Tuple[PdoConfig, ...]:
    """Return the PDOs of ``layout``, a name in ``simulated_drives.LAYOUTS``."""
    return globals()[LAYOUTS[layout]]()
