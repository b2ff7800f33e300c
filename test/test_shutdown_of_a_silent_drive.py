"""A drive silent at shutdown gets its stop and nothing commanding it after; the node exits.

The node runs as its own process (test_drive_safety's rig); the drive (durand) stops answering
right before the signal, so neither the stop's SDO download nor the statusword read after it
is answered, and no TPDO shows the stop.
"""

import signal

import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    layout_pdos,
    nothing_to_the_drive_after,
    QUICK_STOP,
    rig,
    stop_frame_after,
    stop_with,
)

from cbcan_ros.msg import SdoAccess
from cbcan_ros.srv import SdoBatch

from conftest import wait_until

NODE = 7


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


def test_a_silent_drive_busy_with_a_batch_gets_its_stop_and_the_batch_ends(rig):  # noqa: F811
    # A caller's batch of reads runs into the silence: each read would wait out its time
    # with the stop queued behind it, past the wait of shutdown, so the stop never went out.
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos('combined'))
    axis.enable_moving()
    axis.wait_state('OPERATION_ENABLED')
    axis.stop_streams()
    axis.drive.stop()
    batch_objects = range(0x2100, 0x2104)
    reads = [SdoAccess(node_id=NODE, index=index) for index in batch_objects]
    since = axis.recorder.mark()
    batch = axis.client(SdoBatch, 'sdo_batch').call_async(
        SdoBatch.Request(accesses=reads, timeout=20.0))

    def uploads(start: int) -> list:
        return [m for m in axis.recorder.messages(start) if m.arbitration_id == 0x600 + NODE
                and m.data[0] == 0x40 and m.data[1] | m.data[2] << 8 in batch_objects]
    wait_until(lambda: uploads(since), ANSWER, "the batch's first read on the bus")
    stop_with(axis, signal.SIGINT)
    request = axis.recorder.first(
        lambda m: m.arbitration_id == 0x600 + NODE and bytes(m.data[:4]) == b'\x2b\x40\x60\x00'
        and m.data[4] | m.data[5] << 8 == QUICK_STOP, 'the quick stop download', since)
    nothing_to_the_drive_after(axis, request, 'the quick stop')
    assert len(uploads(since)) == 1, 'the batch went on reading after shutdown began'
    wait_until(batch.done, ANSWER, 'the batch answered')
    assert all(not result.success for result in batch.result().results)
