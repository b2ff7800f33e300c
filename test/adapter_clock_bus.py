"""A python-can bus whose received frames carry an adapter's clock, not the host's.

Adapters with a timestamp clock of their own (Kvaser, PCAN, many USB adapters) stamp frames
with a clock whose offset to the host is set once at open (PCAN's from an estimate of the
boot time) and then drifts; some stamp nothing (0). ``AdapterClockBus`` wraps another
python-can bus on the same channel and rewrites the timestamp of every frame it receives:

* ``offset:S``: the host's wall clock plus S seconds (S may be negative: a lagging clock);
* ``drift:R``: a clock that starts right and then runs at 1 + R times the host's speed;
* ``zero``: every timestamp 0;
* ``boot``: seconds since the host booted, as a clock relative to the adapter's start.

In a test process, :func:`register` makes ``can.Bus(interface='adapter_clock', ...)`` create
one. A node started as a separate process finds it through :func:`plugin_path`, a folder to
put on its ``PYTHONPATH`` that announces the bus as a python-can interface plugin (the entry
point group ``can.interface``), exactly as a third-party adapter package does. Options
(``clock``, ``inner_interface`` and the inner bus's own, e.g. ``port``) come as bus keyword
arguments, also through python-can's ``CAN_CONFIG`` environment variable.
"""

import pathlib
import time
from typing import Callable, Optional

import can

from faulty_bus import register_backend

INTERFACE_NAME = 'adapter_clock'
HERE = pathlib.Path(__file__).resolve().parent


def clock(description: str) -> Callable[[], float]:
    """Return the adapter clock ``description`` names (see the module's documentation)."""
    kind, _, value = description.partition(':')
    if kind == 'offset':
        offset = float(value)
        return lambda: time.time() + offset
    if kind == 'drift':
        rate, start = float(value), time.time()
        return lambda: start + (time.time() - start) * (1.0 + rate)
    if kind == 'zero':
        return lambda: 0.0
    if kind == 'boot':
        return time.monotonic
    raise ValueError(f'unknown adapter clock {description!r}')


class AdapterClockBus(can.BusABC):
    """Another python-can bus, its received frames stamped by an adapter clock."""

    def __init__(self, channel, clock: str = 'offset:0', inner_interface: str = 'virtual',
                 **kwargs):
        self._clock = globals()['clock'](clock)
        self._inner = can.Bus(interface=inner_interface, channel=channel, **kwargs)
        self.channel_info = f'{inner_interface} {channel} with an adapter clock {clock}'
        super().__init__(channel)

    def _recv_internal(self, timeout: Optional[float]):
        message = self._inner.recv(timeout)
        if message is not None:
            message.timestamp = self._clock()
        return message, False

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        """Send through the inner bus."""
        self._inner.send(msg, timeout)

    def shutdown(self) -> None:
        """Close this bus and the inner one."""
        super().shutdown()
        self._inner.shutdown()


def register() -> None:
    """Make ``can.Bus(interface='adapter_clock', ...)`` work in this process (idempotent)."""
    register_backend(INTERFACE_NAME, __name__, AdapterClockBus.__name__)


def plugin_path(folder: pathlib.Path) -> str:
    """Announce this bus as an installed python-can plugin in ``folder``; return a PYTHONPATH.

    The path holds ``folder`` (the plugin's metadata) and this test folder (the module).
    """
    info = folder / 'cbcan_test_adapter_clock-1.0.dist-info'
    info.mkdir(parents=True, exist_ok=True)
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: cbcan-test-adapter-clock\n'
                                   'Version: 1.0\n')
    (info / 'entry_points.txt').write_text(
        f'[can.interface]\n{INTERFACE_NAME} = {__name__}:{AdapterClockBus.__name__}\n')
    return f'{folder}:{HERE}'
