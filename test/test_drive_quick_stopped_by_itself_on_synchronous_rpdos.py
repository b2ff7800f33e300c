"""A drive that quick-stops by itself is not left running by a target frame on its way.

Velocity targets streamed; the drive's quick stop option 6 keeps it in QUICK_STOP_ACTIVE,
where "enable operation" is transition 16. The 'vendor' layout with every RPDO synchronous,
the gateway producing SYNC (test_drive_stops_with_synchronous_rpdos): the frame waits in the
drive for the next SYNC; and the 'combined' layout, event-driven: the frame arrives just
after the drive stopped.
"""

import struct
import threading
import time

from test_drive_safety import ANSWER, HALT, layout_pdos, NODE, rig  # noqa: F401 (rig: fixture)
from test_drive_stops_with_synchronous_rpdos import Applied, streaming, summary, syncs_pass

from cbcan_ros.simulation.durand.drive_objects import QUICK_STOP_OPTION

from conftest import wait_until

RPDO4 = 0x500 + NODE  # controlword, target velocity (both layouts)


def quick_stop_with_the_next_target_frame(drive, held: bool) -> None:
    """Fire the drive's quick-stop input with its next target frame ("enable operation").

    ``held``: once the drive has taken the frame (it waits there for the next SYNC); else a
    moment before the frame arrives.
    """
    subscriptions = drive._network._subscriptions
    handle = subscriptions[RPDO4]
    armed = [True]

    def intercepted(cob_id, msg):
        fire = armed[0] and struct.unpack_from('<H', msg)[0] & 0x8F == 0x0F
        if fire:
            armed[0] = False
            if not held:
                drive.set_value(0x6040, 0, 0x0002)
        handle(cob_id, msg)
        if fire and held:
            threading.Thread(target=drive.set_value, args=(0x6040, 0, 0x0002)).start()
    subscriptions[RPDO4] = intercepted


def left_stopped(axis, applied: Applied, start: float, frame: str) -> None:
    """Wait for the drive to stand, out of OPERATION_ENABLED or halted; else say what it did."""
    drive = axis.drive

    def stopped() -> bool:
        words = [e[2] for e in applied.since(start) if e[1] == 'cw']
        return drive.velocity == 0 and (drive.drive_state != 'OPERATION_ENABLED'
                                        or bool(words and words[-1] & HALT))
    try:
        wait_until(stopped, ANSWER, 'the drive stopped')
    except AssertionError:
        raise AssertionError(
            f'the drive runs on at {drive.velocity} in {drive.drive_state} after it '
            f'quick-stopped by itself and took a {frame} target frame; drive_state says '
            f'{axis.latest().state}, nothing halts it (needs a fresh enable: targets refused, '
            f'no command timeout); applied: {summary(applied.since(start))}:\n'
            f'{axis.node.output()[-1500:]}') from None


def test_a_drive_that_quick_stops_by_itself_is_not_left_running_by_a_held_target_frame(rig):  # noqa: F811
    # The drive quick-stops by itself (its quick-stop input, another master), option 6: it
    # stays in QUICK_STOP_ACTIVE. A target frame of the stream reached it just before, and
    # waits there for the next SYNC with the controlword "enable operation": transition 16,
    # the drive runs again (docs/drives.md: such a frame "is the only one it may get").
    # Whatever it got, it must not be left running at a velocity nobody commands: the gateway
    # refuses the robot program's targets (it needs a fresh enable), so neither can they stop
    # it nor can the command timeout, which skips a drive that needs an enable.
    axis, applied = streaming(rig, 0.01, '-p', 'drives.command_timeout:=0.3')
    start = time.monotonic()
    quick_stop_with_the_next_target_frame(axis.drive, held=True)
    applied.first(lambda e: e[1] == 'state' and e[2] == 'QUICK_STOP_ACTIVE',
                  'the drive quick-stopping by itself', start)
    # The robot program sees the drive stopped and stops streaming; two SYNCs later the
    # drive has applied whatever frame it held.
    axis.stop_streams()
    syncs_pass(axis, 2, axis.recorder.mark())
    left_stopped(axis, applied, start, 'held')


def test_a_drive_that_quick_stops_by_itself_is_not_left_running_by_a_late_target_frame(rig):  # noqa: F811
    # The 'vendor' layout as shipped, event-driven RPDOs, no SYNC: the drive's quick-stop
    # input fires just before a target frame of the stream (controlword "enable operation"
    # and target velocity, RPDO 4) arrives, on its way: transition 16, the drive runs again.
    axis = rig('-p', 'drives.command_timeout:=0.3', pdos=layout_pdos('vendor'))
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))
    applied = Applied(axis.drive)
    axis.enable_moving()
    start = time.monotonic()
    quick_stop_with_the_next_target_frame(axis.drive, held=False)
    applied.first(lambda e: e[1] == 'state' and e[2] == 'QUICK_STOP_ACTIVE',
                  'the drive quick-stopping by itself', start)
    axis.stop_streams()
    left_stopped(axis, applied, start, 'late')
