"""No raw frame of a caller reaches a drive after its stop, at shutdown or at deactivate.

docs/services.md, Shutdown: "first it stops sending raw frames ..., then it sends every
powered drive its stop"; docs/lifecycle.md: deactivate sends every powered drive
``drives.on_shutdown``, and a node that is not active refuses every frame to send. A robot
program that sends a drive's RPDO itself through ``~/send_frames`` and ``~/to_can_bus`` (its
id opened with the full mask in ``raw.send_allow``, as docs/raw_frames.md allows) keeps
sending through the signal or the transition: nothing of it may reach the drive after the
quick stop, which it would undo. The node runs as its own process (test_drive_safety's rig),
the drive is durand's.
"""

import signal
import struct
import threading

from can_msgs.msg import Frame
from lifecycle_msgs.msg import Transition
import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    configure_once_read,
    CSV,
    MANAGED,
    managed_transition,
    nothing_to_the_drive_after,
    QUICK_STOP,
    rig,
    RPDO1,
    shown,
    standing_still,
    stop_frame_after,
    stop_with,
)

from cbcan_ros.msg import CanFrame
from cbcan_ros.srv import SendFrames

from conftest import wait_until

ENABLE_OPERATION = 0x000F


@pytest.mark.parametrize('way', ['shutdown', 'deactivate'])
def test_no_raw_frame_of_a_caller_reaches_a_drive_after_its_stop(rig, way):  # noqa: F811
    allowed = ('-p', f'raw.send_allow:=["{RPDO1:X}:7FF"]')
    if way == 'deactivate':
        axis = rig(*MANAGED, *allowed, program='cbcan_lifecycle_node')
        configure_once_read(axis)
        managed_transition(axis, Transition.TRANSITION_ACTIVATE)
    else:
        axis = rig('-p', 'drives.command_timeout:=0.0', *allowed)
    axis.enable_moving()
    axis.stop_streams()
    sender = axis.client(SendFrames, 'send_frames')
    topic = axis.client_node.create_publisher(Frame, f'{axis.name}/to_can_bus', 10)
    # RPDO 1 of the combined layout: controlword, target position, mode (CSV).
    data = struct.pack('<HiB', ENABLE_OPERATION, 0, CSV).ljust(8, b'\0')
    # Many frames a call: a call under way as the stop begins goes on sending them.
    request = SendFrames.Request(frames=[CanFrame(id=RPDO1, dlc=7, data=list(data))] * 100)
    stop = threading.Event()

    def send() -> None:
        while not stop.is_set():
            sender.call_async(request)
            topic.publish(Frame(id=RPDO1, dlc=7, data=list(data)))
            stop.wait(0.005)
    thread = threading.Thread(target=send, daemon=True)
    start = axis.recorder.mark()
    thread.start()
    try:
        wait_until(lambda: any(m.arbitration_id == RPDO1 and bytes(m.data) == data[:7]
                               for m in axis.recorder.messages(start)), 15.0,
                   "the program's raw frames on the bus")
        before = axis.recorder.mark()
        if way == 'deactivate':
            managed_transition(axis, Transition.TRANSITION_DEACTIVATE)
            axis.drive_reaches(standing_still, 'the drive stopped')
        else:
            stop_with(axis, signal.SIGINT)
    finally:
        stop.set()
        thread.join()
    quick_stop = stop_frame_after(axis, QUICK_STOP, before)
    axis.recorder.mark()
    after = [m for m in axis.recorder.messages(quick_stop + 1) if m.arbitration_id == RPDO1]
    assert not after, (f'{len(after)} raw frames to the drive after its quick stop (the drive '
                       f'is {axis.drive.drive_state} at velocity {axis.drive.velocity}): '
                       f'{shown(after[:5])}')
    nothing_to_the_drive_after(axis, quick_stop, f'the quick stop at {way}')
