"""A managed node deactivated stops a drive busy with a caller's SDO batch first.

docs/drives.md: "The gateway stops (Ctrl-C, SIGTERM, a managed node deactivated, ...): every
powered drive is sent drives.on_shutdown by SDO ... The stop goes first: SDO transfers under
way with a drive (a caller's long upload or batch ...) are ended, and a batch sends none of
its remaining accesses". The node runs as its own process (test_drive_safety's rig); the drive
(durand) answers, but slowly: each read of its object 0x2200 takes a second.
"""

from lifecycle_msgs.msg import Transition
import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    configure_once_read,
    MANAGED,
    managed_transition,
    nothing_to_the_drive_after,
    QUICK_STOP,
    rig,
    shown,
    standing_still,
    stop_frame_after,
)

from cbcan_ros.msg import SdoAccess
from cbcan_ros.simulation.durand.dictionary import SLOW_INDEX
from cbcan_ros.srv import SdoBatch, SdoRead

from conftest import wait_until

NODE = 7
SLOW_READ = 1.0  # s the drive takes to answer each read of SLOW_INDEX
READS = 8


def the_stop(axis, since: int) -> int:
    """Return the position of the quick stop download from ``since`` on; fail with the log."""
    try:
        return stop_frame_after(axis, QUICK_STOP, since)
    except AssertionError as error:
        raise AssertionError(f'{error}\nthe drive: {axis.drive.drive_state} at velocity '
                             f'{axis.drive.velocity}; the node log:\n'
                             f'{axis.node.output()[-2000:]}') from None


def moving_and_slow_to_read(rig):  # noqa: F811
    """Return an active managed node's rig, its drive moving and SLOW_READ s to read."""
    axis = rig(*MANAGED, '-p', 'sdo.timeout:=5.0', program='cbcan_lifecycle_node')
    configure_once_read(axis)
    managed_transition(axis, Transition.TRANSITION_ACTIVATE)
    axis.enable_moving()
    axis.stop_streams()
    axis.drive.slow_read_delay = SLOW_READ
    return axis


def slow_uploads(axis, since: int) -> list:
    """Return the positions of the upload requests of SLOW_INDEX from ``since`` on."""
    return [number for number, message in enumerate(axis.recorder.messages(since), since)
            if message.arbitration_id == 0x600 + NODE and message.data[0] == 0x40
            and message.data[1] | message.data[2] << 8 == SLOW_INDEX]


@pytest.mark.parametrize('transition', [Transition.TRANSITION_DEACTIVATE,
                                        Transition.TRANSITION_ACTIVE_SHUTDOWN],
                         ids=['deactivate', 'shutdown'])
def test_a_managed_node_stops_a_drive_busy_with_a_batch_before_the_batch_goes_on(
        rig, transition):  # noqa: F811
    axis = moving_and_slow_to_read(rig)
    reads = [SdoAccess(node_id=NODE, index=SLOW_INDEX) for _ in range(READS)]
    start = axis.recorder.mark()
    batch = axis.client(SdoBatch, 'sdo_batch').call_async(
        SdoBatch.Request(accesses=reads, timeout=60.0))
    wait_until(lambda: slow_uploads(axis, start), ANSWER, "the batch's first read on the bus")
    before = axis.recorder.mark()
    managed_transition(axis, transition)
    request = the_stop(axis, before)
    uploads = slow_uploads(axis, start)
    sent_first = [number for number in uploads if number < request]
    assert len(sent_first) <= 2, (
        f'{len(sent_first)} reads of the batch went out before the stop '
        f'({len(uploads)} in all): {shown(axis.recorder.messages(before))}')
    axis.drive_reaches(standing_still, 'the drive stopped')
    wait_until(batch.done, ANSWER, 'the batch answered')
    axis.recorder.mark()
    nothing_to_the_drive_after(axis, request, 'the quick stop')


def test_deactivate_stops_a_drive_answering_a_slow_read(rig):  # noqa: F811
    # One read of a caller that takes the drive a second to answer: the stop, queued behind
    # it, must still reach the drive.
    axis = moving_and_slow_to_read(rig)
    start = axis.recorder.mark()
    read = axis.client(SdoRead, 'sdo_read').call_async(
        SdoRead.Request(node_id=NODE, index=SLOW_INDEX, timeout=5.0))
    wait_until(lambda: slow_uploads(axis, start), ANSWER, 'the read on the bus')
    before = axis.recorder.mark()
    managed_transition(axis, Transition.TRANSITION_DEACTIVATE)
    request = the_stop(axis, before)
    axis.drive_reaches(standing_still, 'the drive stopped')
    wait_until(read.done, ANSWER, 'the read answered')
    axis.recorder.mark()
    nothing_to_the_drive_after(axis, request, 'the quick stop')
