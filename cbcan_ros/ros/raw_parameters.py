"""The raw CAN parameters ``raw.filters`` and ``raw.send_allow``: declared, checked, parsed.

Declared with descriptors by :class:`~.config.NodeParameters`; a filter that does not parse
stops the node naming the parameter and the filter. The two topics carry
``can_msgs/msg/Frame``, a ROS package of its own (``ros-jazzy-can-msgs``): the gateway builds
and runs without it, and only refuses to start when one of these parameters asks for the
topics and the package is not installed, saying what to install.
"""

import importlib
from typing import Callable, List

from rclpy.parameter import Parameter

from ..core.raw.filters import FILTER_FORMAT, FrameFilters, parse_filters
from ..core.raw.frames import RawSettings
from .parameter_checks import ConfigurationError

CAN_MSGS_INSTALL = ('sudo apt install ros-jazzy-can-msgs (rosdep installs it from package.xml), '
                    'or leave raw.filters and raw.send_allow empty')


def declare(declare_parameter: Callable) -> None:
    """Declare ``raw.filters`` and ``raw.send_allow`` through ``declare_parameter``."""
    declare_parameter(
        'raw.filters', Parameter.Type.STRING_ARRAY,
        'Raw CAN frames to publish on ~/from_can_bus (can_msgs/msg/Frame), as candump filters '
        'them: ["0:0"] every standard frame (CANopen included), ["18FF0000:1FFF0000"] '
        'extended frames 0x18FFxxxx, "#FFFFFFFF" error frames too. Empty = none (the raw '
        'bridge is off). Frames the gateway sends are not published back',
        additional_constraints=f'each {FILTER_FORMAT}')
    declare_parameter(
        'raw.send_allow', Parameter.Type.STRING_ARRAY,
        'Ids that programs may send on ~/to_can_bus and ~/send_frames, in the same syntax '
        '(e.g. "18FF0000:1FFF0000", "321:7FF"). Empty = nothing may be sent. Ids the gateway '
        'uses for CANopen (NMT, SYNC, TIME, EMCY, SDO, heartbeats, LSS, the PDOs of its '
        'devices) are refused even inside a wide entry; only an entry naming the id with the '
        'full mask (e.g. "60A:7FF") opens one. read_only refuses every frame',
        additional_constraints=f'each id:mask or id~mask ({FILTER_FORMAT})')


def _parsed(name: str, entries: List[str], errors: bool) -> FrameFilters:
    try:
        return parse_filters(entries, errors)
    except ValueError as error:
        raise ConfigurationError(name, entries, f'holds a filter that does not parse: {error}',
                                 FILTER_FORMAT if errors else
                                 f'id:mask or id~mask entries ({FILTER_FORMAT})') from None


def settings(strings: Callable[[str], List[str]]) -> RawSettings:
    """Return the raw bridge's settings; raise ConfigurationError naming a wrong parameter.

    ``strings(name)`` returns a string-array parameter's value.
    """
    filters = _parsed('raw.filters', strings('raw.filters'), True)
    send_allow = _parsed('raw.send_allow', strings('raw.send_allow'), False)
    for name, parsed in (('raw.filters', filters), ('raw.send_allow', send_allow)):
        if not parsed.empty and not can_msgs_installed():
            raise ConfigurationError(
                name, strings(name), 'needs the ROS package can_msgs (can_msgs/msg/Frame of '
                '~/from_can_bus and ~/to_can_bus), which is not installed', CAN_MSGS_INSTALL)
    return RawSettings(filters, send_allow)


def can_msgs_installed() -> bool:
    """Return whether ``can_msgs/msg/Frame`` can be imported."""
    try:
        importlib.import_module('can_msgs.msg')
    except ImportError:
        return False
    return True
