"""A drive's state as shown is its newest: an SDO answer never hides a later TPDO's.

The gateway reads a drive by SDO where no TPDO brings its feedback (a drive pre-operational,
a drive being re-read after a boot) and takes its TPDOs as they come. SDO answers are taken
on an SDO thread, TPDOs on the bus's dispatch thread: an answer the drive gave before a TPDO
can be taken after it. Each test holds such an answer back until the TPDO is in, as a busy
machine does now and then, and checks what a robot program sees.

Once a defect (before the change that added this file): the older answer won. A drive that
entered OPERATION_ENABLED just as the gateway saw it go OPERATIONAL was shown SWITCHED_ON
right after ``enable`` answered success, and refused its first target.

A TPDO that comes before the gateway knows the drive's PDO mapping cannot be taken. Sent on
change only, it is not sent again: the gateway reads by SDO what TPDOs bring from then on.
Once a defect: the drive stayed shown in the state before, and an enable timed out now and
then (the mapping read finished while the enable's first step went by SDO).
"""

from concurrent.futures import Future
from dataclasses import replace
import threading

from test_drive_bus_faults import hold_next_answer
from test_drives import CSV, NODE, PDOS, rig, WAIT, watch  # noqa: F401 - rig: a fixture

from cbcan_ros.core.drives import cia402
from cbcan_ros.core.drives import cycle as drive_cycle
from cbcan_ros.core.pdo.parameters import PdoParameters

from conftest import wait_until

PRE_OPERATIONAL, OPERATIONAL, RESET = 128, 1, 129  # NMT commands; the drive's states:
DRIVE_PRE_OPERATIONAL, DRIVE_OPERATIONAL = 127, 5
ERROR = 0x2310  # continuous over-current
TPDO_1, HEARTBEAT = 0x180 + NODE, 0x700 + NODE
# The statusword TPDO on change only, with no event timer to repeat it.
ON_CHANGE = tuple(replace(pdo, event_timer=0) if (pdo.kind, pdo.number) == ('tpdo', 1)
                  else pdo for pdo in PDOS)


def nmt(axis, command: int, drive_state: int) -> None:
    """Send NMT ``command`` to the drive; wait until it is there, and its heartbeat says so.

    From then on the gateway reads by SDO only what no TPDO brings in that state.
    """
    assert axis.gateway.call('nmt_command', node_id=NODE, command=command).success
    monitor = axis.gateway.node.gateway.monitor
    wait_until(lambda: axis.drive.state == drive_state
               and monitor.status(NODE).state == drive_state, WAIT,
               f'the drive in NMT state {drive_state}, heard so')


def hold_mapping_reads(monkeypatch) -> threading.Event:
    """Make the gateway take the PDO mappings it reads only once the returned event is set.

    Each read goes to the device at once; its result is held.
    """
    read, release = PdoParameters.read, threading.Event()

    def held(self, *args, **kwargs):
        result = read(self, *args, **kwargs)
        release.wait(WAIT)
        return result
    monkeypatch.setattr(PdoParameters, 'read', held)
    return release


def shows_fault(frame) -> bool:
    """Return whether ``frame`` is the drive's TPDO 1 with a statusword saying FAULT."""
    return (frame.arbitration_id == TPDO_1
            and cia402.state_of(frame.data[0] | frame.data[1] << 8) == 'FAULT')


def drive_record(axis):
    """Return the gateway's record of the drive."""
    return axis.gateway.node.gateway.drives._drives[NODE]


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


def test_a_fault_sent_before_the_gateway_knew_the_mapping_is_shown(rig, monkeypatch):  # noqa: F811
    release = hold_mapping_reads(monkeypatch)
    try:
        axis = rig(pdos=ON_CHANGE)
        wait_until(lambda: drive_record(axis).polled, WAIT, 'the first SDO read of feedback')
        monkeypatch.setattr(drive_cycle, 'POLL_PERIOD', 60.0)  # no periodic read finds it
        bus, frames = axis.gateway.raw_bus(), []
        try:
            axis.drive.inject_fault(ERROR)
            watch(bus, frames, lambda seen: any(map(shows_fault, seen)), 'the FAULT TPDO')
            fault = next(filter(shows_fault, frames))
            watch(bus, frames, lambda seen: seen[-1].arbitration_id == HEARTBEAT,
                  'a heartbeat after it')
            beat = frames[-1]
        finally:
            bus.shutdown()
        assert beat.timestamp > fault.timestamp
        # The gateway takes frames in order: once it has the heartbeat, it had the TPDO.
        monitor = axis.gateway.node.gateway.monitor
        wait_until(lambda: monitor.status(NODE).last_seen >= beat.timestamp, WAIT,
                   'the gateway hearing the drive after its FAULT TPDO')
    finally:
        release.set()
    wait_until(lambda: axis.latest_state() == 'FAULT', WAIT, 'drive_state FAULT')


def test_an_enable_answered_by_a_tpdo_before_the_mapping_was_known_succeeds(
        rig, monkeypatch):  # noqa: F811
    release = hold_mapping_reads(monkeypatch)
    try:
        axis = rig(pdos=ON_CHANGE)
        wait_until(lambda: drive_record(axis).polled, WAIT, 'the first SDO read of feedback')
        monkeypatch.setattr(drive_cycle, 'POLL_PERIOD', 60.0)  # no periodic read finds it
        objects = drive_record(axis).objects
        write = objects.write

        def mapping_known_before_the_answer(values, timeout):
            # The drive took the step and sent its statusword; the gateway then learns the
            # mapping, and only then hears that the step went out.
            sent, late = write(values, timeout), Future()
            if cia402.CONTROLWORD not in values or release.is_set():
                return sent

            def hand_over(done):
                release.set()
                try:
                    wait_until(lambda: cia402.STATUSWORD in objects.mapped_feedback(), WAIT,
                               'the mapping taken')
                finally:
                    late.set_result(done.result())
            sent.add_done_callback(lambda done: threading.Thread(
                target=hand_over, args=(done,), daemon=True).start())
            return late
        objects.write = mapping_known_before_the_answer
        assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
        axis.enable(CSV)
        assert axis.drive.drive_state == 'OPERATION_ENABLED'
    finally:
        release.set()
