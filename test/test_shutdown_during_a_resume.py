"""A signal while a resume waits for the SYNC that applies it: one answer, the drive stops.

The node runs as its own process (test_drive_safety's rig) with synchronous RPDOs
(the combined layout, synchronous) and a slow SYNC, so the resume of a halted drive waits
long for the SYNC that applies its release. The signal comes meanwhile: the resume is
answered once, the drive is quick-stopped and nothing commanding it follows the stop; the
drive ends standing.
"""

import signal
import time

from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    COMMAND_TIMEOUT,
    DriveCommand,
    NODE,
    nothing_to_the_drive_after,
    QUICK_STOP,
    rig,
    standing_still,
    stop_with,
)

from cbcan_ros.core.drives.cia402 import HALT
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos

from conftest import wait_until

SYNC_PERIOD = 0.8


def test_a_signal_while_a_resume_waits_for_its_sync(rig):  # noqa: F811
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', f'sync.period:={SYNC_PERIOD}',
               pdos=default_drive_pdos(transmission_type=1))
    # Each of the enable's three steps waits for a SYNC to be sent, one to be applied and
    # one to be shown: about three periods, 7 s of the 10 s a command gets by default
    # (a busy machine took longer once).
    axis.enable_moving(timeout=COMMAND_TIMEOUT + 12 * SYNC_PERIOD)
    axis.stop_streams()
    halted = axis.command('halt')
    assert halted.success, halted.message
    answers = []
    client = axis.client(DriveCommand, 'drive_command')
    before = axis.recorder.mark()
    future = client.call_async(DriveCommand.Request(node_id=NODE, command='resume',
                                                    timeout=10.0))
    future.add_done_callback(lambda done: answers.append(done.result()))
    # The resume's frame is out: the SYNC that applies it is most of a period away (it
    # waits for two), so the signal below comes while the resume waits, however slow the
    # machine is to wake this thread.
    try:
        axis.recorder.first(
            lambda m: m.arbitration_id == 0x200 + NODE and not m.data[1] & (HALT >> 8),
            "the resume's controlword without halt", before)
    except AssertionError as error:  # a resume refused sends nothing: say what it answered
        # A resume sent by SDO (the gateway counting no RPDO of the drive usable) is
        # answered at once: the answer says which.
        raise AssertionError(f'{error}; the resume answered {answers}; the drive shows '
                             f'{axis.latest()}; the gateway logged: '
                             f'{axis.node.output()[-2000:]}') from None
    assert not answers, answers
    since = axis.recorder.mark()
    stop_with(axis, signal.SIGINT)
    wait_until(lambda: answers, ANSWER, 'the resume answered')
    time.sleep(0.5)
    assert len(answers) == 1, answers
    request = axis.recorder.first(
        lambda m: m.arbitration_id == 0x600 + NODE and bytes(m.data[:4]) == b'\x2b\x40\x60\x00'
        and m.data[4] | m.data[5] << 8 == QUICK_STOP, 'the quick stop download', since)
    nothing_to_the_drive_after(axis, request, 'the quick stop')
    axis.drive_reaches(standing_still, 'the drive stopped')
    assert axis.latest().state != 'OPERATION_ENABLED', axis.latest()
