"""At deactivate no raw frame of a caller reaches a drive after its stop.

docs/lifecycle.md: deactivate sends every powered drive ``drives.on_shutdown`` ("a
deactivated gateway commands no drive"), and docs/raw_frames.md: a managed node that is not
active refuses every frame to send. A robot program that sends a drive's RPDO itself through
``~/send_frames`` or ``~/to_can_bus`` (its id opened with the full mask) keeps sending through
the transition: nothing of it may reach the drive after the quick stop, which it would undo.
"""

import struct
import threading

from can_msgs.msg import Frame
from lifecycle_msgs.msg import Transition
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
)

from cbcan_ros.msg import CanFrame
from cbcan_ros.srv import SendFrames

from conftest import wait_until

ENABLE_OPERATION = 0x000F


def test_no_raw_frame_of_a_caller_reaches_a_drive_after_its_stop_at_deactivate(rig):  # noqa: F811
    axis = rig(*MANAGED, '-p', f'raw.send_allow:=["{RPDO1:X}:7FF"]',
               program='cbcan_lifecycle_node')
    configure_once_read(axis)
    managed_transition(axis, Transition.TRANSITION_ACTIVATE)
    axis.enable_moving()
    axis.stop_streams()
    sender = axis.client(SendFrames, 'send_frames')
    topic = axis.client_node.create_publisher(Frame, f'{axis.name}/to_can_bus', 10)
    # RPDO 1 of the combined layout: controlword, target position, mode (CSV).
    data = struct.pack('<HiB', ENABLE_OPERATION, 0, CSV).ljust(8, b'\0')
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
        managed_transition(axis, Transition.TRANSITION_DEACTIVATE)
        quick_stop = stop_frame_after(axis, QUICK_STOP, before)
        axis.drive_reaches(standing_still, 'the drive stopped')
        axis.recorder.mark()
    finally:
        stop.set()
        thread.join()
    after = [m for m in axis.recorder.messages(quick_stop + 1) if m.arbitration_id == RPDO1]
    assert not after, (f'{len(after)} raw frames to the drive after its quick stop (the drive '
                       f'is {axis.drive.drive_state} at velocity {axis.drive.velocity}): '
                       f'{shown(after[:5])}')
    nothing_to_the_drive_after(axis, quick_stop, 'the quick stop at deactivate')
