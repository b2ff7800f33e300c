"""A drive silent at shutdown gets its stop and nothing commanding it after; the node exits.

The node runs as its own process (test_drive_safety's rig); the drive (durand) stops answering
right before the signal, so neither the stop's SDO download nor the statusword read after it
is answered, and no TPDO shows the stop.
"""

import signal

import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    layout_pdos,
    nothing_to_the_drive_after,
    QUICK_STOP,
    rig,
    stop_frame_after,
    stop_with,
)

from conftest import wait_until


@pytest.mark.parametrize('layout, sync', [
    ('combined', ()), ('ros2_canopen', ('-p', 'sync.period:=0.01')), ('sdo_only', ())],
    ids=['combined', 'ros2_canopen-sync', 'sdo_only'])
def test_a_silent_drive_gets_its_stop_and_nothing_after(rig, layout, sync):  # noqa: F811
    axis = rig('-p', 'drives.command_timeout:=0.0', *sync, pdos=layout_pdos(layout))
    axis.enable_moving()
    axis.wait_state('OPERATION_ENABLED')
    axis.stop_streams()
    since = axis.recorder.mark()
    axis.drive.stop()
    stop_with(axis, signal.SIGINT)
    request = axis.recorder.first(
        lambda m: m.arbitration_id == 0x607 and bytes(m.data[:4]) == b'\x2b\x40\x60\x00'
        and m.data[4] | m.data[5] << 8 == QUICK_STOP, 'the quick stop download', since)
    nothing_to_the_drive_after(axis, request, 'the quick stop')
    wait_until(lambda: axis.latest().state == 'UNKNOWN', 5.0,
               'the last drive_state UNKNOWN')
