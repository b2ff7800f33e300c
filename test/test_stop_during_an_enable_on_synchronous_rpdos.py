"""A stop that comes while an enable is under way on synchronous RPDOs is not undone by it.

The 'vendor' layout with every RPDO synchronous, the gateway producing SYNC: an enable's
steps (0x06, 0x07, 0x0F) go in RPDO frames applied at the SYNCs that follow. A signal, or a
deactivate of the managed node (SYNC goes on then), comes after the first step went out:
the drive must not end in OPERATION_ENABLED, nor enter it after it applied the stop.
"""

import signal
import threading
import time

from lifecycle_msgs.msg import Transition
import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    controlword_of,
    CSV,
    managed_transition,
    rig,
    stop_with,
)
from test_drive_stops_with_synchronous_rpdos import (
    Applied,
    summary,
    synchronous_axis,
    syncs_pass,
)

from cbcan_ros.srv import DriveCommand

from conftest import wait_until


@pytest.mark.parametrize('how', ['SIGINT', 'deactivate'])
def test_a_stop_during_an_enable_on_synchronous_rpdos_is_not_undone(rig, how):  # noqa: F811
    managed = how == 'deactivate'
    axis = synchronous_axis(rig, 0.01, *(() if managed else ('-p', 'drives.command_timeout:=0.0')),
                            managed=managed)
    axis.nmt_start()
    applied = Applied(axis.drive)
    client = axis.client(DriveCommand, 'drive_command')
    start = time.monotonic()
    since = axis.recorder.mark()
    client.call_async(DriveCommand.Request(node_id=7, command='enable', mode=CSV, timeout=10.0))
    axis.recorder.first(lambda m: controlword_of(m) in (0x06, 0x07)
                        or (m.arbitration_id in (0x207, 0x307, 0x407, 0x507)
                            and m.data[0] in (0x06, 0x07)),
                        'the first step of the enable on the bus', since)
    if managed:
        thread = threading.Thread(target=managed_transition,
                                  args=(axis, Transition.TRANSITION_DEACTIVATE))
        thread.start()
        thread.join(ANSWER)
        syncs_pass(axis, 20, axis.recorder.mark())
    else:
        stop_with(axis, signal.SIGINT)
    wait_until(lambda: axis.drive.velocity == 0, ANSWER, 'the drive standing')
    events = applied.since(start)
    stops = [n for n, e in enumerate(events) if e[1] == 'cw' and e[2] in (0x02, 0x00)]
    # Not powered yet when the gateway stopped (READY_TO_SWITCH_ON), it is sent no stop.
    again = [e for e in events[stops[0] if stops else 0:]
             if e[1] == 'state' and e[2] == 'OPERATION_ENABLED']
    assert not again and axis.drive.drive_state != 'OPERATION_ENABLED', \
        f'the drive enabled after the stop ({how}): {summary(events)}'
