"""A drive's state as shown is its newest: an SDO answer never hides a later TPDO's.

The gateway reads a drive by SDO where no TPDO brings its feedback (a drive pre-operational,
a drive being re-read after a boot) and takes its TPDOs as they come. SDO answers are taken
on an SDO thread, TPDOs on the bus's dispatch thread: an answer the drive gave before a TPDO
can be taken after it. Each test holds such an answer back until the TPDO is in, as a busy
machine does now and then, and checks what a robot program sees.

Once a defect (before the change that added this file): the older answer won. A drive that
entered OPERATION_ENABLED just as the gateway saw it go OPERATIONAL was shown SWITCHED_ON
right after ``enable`` answered success, and refused its first target.
"""

from test_drive_bus_faults import hold_next_answer
from test_drives import NODE, rig, WAIT  # noqa: F401 - rig is a fixture used by name

from cbcan_ros.core import cia402

from conftest import wait_until

PRE_OPERATIONAL, OPERATIONAL, RESET = 128, 1, 129  # NMT commands; the drive's states:
DRIVE_PRE_OPERATIONAL, DRIVE_OPERATIONAL = 127, 5
ERROR = 0x2310  # continuous over-current


def nmt(axis, command: int, drive_state: int) -> None:
    """Send NMT ``command`` to the drive; wait until it is there, and its heartbeat says so.

    From then on the gateway reads by SDO only what no TPDO brings in that state.
    """
    assert axis.gateway.call('nmt_command', node_id=NODE, command=command).success
    monitor = axis.gateway.node.gateway.monitor
    wait_until(lambda: axis.drive.state == drive_state
               and monitor.status(NODE).state == drive_state, WAIT,
               f'the drive in NMT state {drive_state}, heard so')


def shown_state(axis) -> str:
    """Return the state the gateway shows callers now."""
    return axis.gateway.node.gateway.drives.status(NODE).state


def test_an_sdo_answer_taken_after_a_newer_tpdo_does_not_show_the_older_state(rig):  # noqa: F811
    axis = rig()
    nmt(axis, PRE_OPERATIONAL, DRIVE_PRE_OPERATIONAL)  # no TPDOs: its statusword read by SDO
    answered, release, taken = hold_next_answer(
        axis, 'read', lambda indexes, _timeout: cia402.STATUSWORD in indexes)
    wait_until(answered.is_set, WAIT, 'the statusword read by SDO')
    assert shown_state(axis) == 'SWITCH_ON_DISABLED'
    nmt(axis, OPERATIONAL, DRIVE_OPERATIONAL)
    axis.drive.inject_fault(ERROR)  # its TPDO tells at once
    wait_until(lambda: shown_state(axis) == 'FAULT' and axis.latest_state() == 'FAULT', WAIT,
               'the fault from the TPDO, shown and published')
    release.set()
    assert taken.wait(WAIT)
    assert shown_state(axis) == 'FAULT'


def test_a_change_the_drive_sends_while_it_is_being_re_read_is_not_lost(rig):  # noqa: F811
    axis = rig()
    answered, release, taken = hold_next_answer(axis, 'read_initial')
    nmt(axis, RESET, DRIVE_PRE_OPERATIONAL)  # it boots, and is re-read
    wait_until(answered.is_set, WAIT, 'the drive re-read by SDO')
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
    nmt(axis, OPERATIONAL, DRIVE_OPERATIONAL)
    axis.drive.inject_fault(ERROR)  # after the re-read's answer, before it is taken
    drive = axis.gateway.node.gateway.drives._drives[NODE]
    wait_until(lambda: drive.unread_state == 'FAULT', WAIT, 'the fault from the TPDO')
    release.set()
    assert taken.wait(WAIT)
    wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), WAIT, 'the drive re-read')
    assert axis.latest_state() == 'FAULT'
    assert shown_state(axis) == 'FAULT'
