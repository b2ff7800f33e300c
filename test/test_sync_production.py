"""SYNC as the gateway's own thread produces it on buses without a timer of their own.

The installed ``cbcan_node`` runs as a child process on a udp_multicast bus of its own (python-
can times no periodic send there: the gateway's SYNC thread sends SYNC, and right after it the
synchronous RPDOs that waited for it). A durand device with a synchronous RPDO lives in this
process, a raw recorder here keeps every frame; this process calls ``~/pdo_write``.
"""

import signal
import threading
import time
import uuid

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState

from cbcan_ros.msg import PdoEntry
from cbcan_ros.simulation.durand.pdos import PdoConfig
from cbcan_ros.srv import PdoWrite

from conftest import wait_for_future, wait_until
from node_process import BusRecorder, call, EDS, private_bus, service_client, START_TIMEOUT

NODE = 5
SYNC = 0x80
ANSWER = 30.0
PDOS = (PdoConfig('rpdo', 1, ((0x2000, 0), (0x2001, 0)), transmission_type=1),
        PdoConfig('rpdo', 2, ((0x2002, 0),), transmission_type=1),
        PdoConfig('tpdo', 1, ((0x2001, 0),), transmission_type=1))


class Rig:
    """A gateway process producing SYNC, device NODE, the bus recorded, a pdo_write client."""

    def __init__(self, start_node, client_node, start_durand, *parameters: str,
                 program: str = 'cbcan_node'):
        group, port = private_bus()
        self.recorder = BusRecorder(group, port)
        self.device = start_durand(NODE, interface='udp_multicast', channel=group,
                                   bus_options={'port': port}, pdos=PDOS)
        name = f'/sync{uuid.uuid4().hex[:8]}/cbcan'
        self.node = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                                '-p', 'can.interface:=udp_multicast',
                                '-p', f'can.channel:={group}',
                                '-p', f'nodes:=[{NODE}]', '-p', f'pdo.nodes:=[{NODE}]',
                                '-p', f'node_{NODE}.eds:={EDS}', *parameters], port, program)
        self.name = name
        self.client_node = client_node
        self.pdo_write = None
        if program == 'cbcan_node':  # a managed node has its services once configured
            self.wait_written()

    def wait_written(self) -> None:
        """Return once a synchronous RPDO was written (the device's mapping read).

        The client waits for the service every time, as a caller of a managed node must:
        configured again, the node serves a new ``pdo_write``, and a request sent before the
        client has found it is lost by DDS (nothing answers it).
        """
        if self.pdo_write is None:
            self.pdo_write = service_client(self.client_node, PdoWrite,
                                            f'{self.name}/pdo_write', self.node)
        elif not self.pdo_write.wait_for_service(timeout_sec=START_TIMEOUT):
            raise AssertionError(f'pdo_write did not appear again within {START_TIMEOUT} s:\n'
                                 f'{self.node.output()}')

        def written():
            began = time.monotonic()
            try:
                answer = call(self.pdo_write, self.request(1.0), 'pdo_write', self.node, ANSWER)
            except AssertionError as error:  # whether the SYNC it waits for came
                raise AssertionError(f'{len(self.syncs(began))} SYNCs on the bus since the '
                                     f'call; {error}') from None
            return answer.success
        wait_until(written, START_TIMEOUT, 'a first synchronous RPDO written (mapping read)')

    @staticmethod
    def request(value: float, pdo: int = 2) -> PdoWrite.Request:
        """Return a pdo_write request of ``value`` in the synchronous RPDO ``pdo``."""
        return PdoWrite.Request(node_id=NODE, pdo=pdo,
                                entries=[PdoEntry(index=0x2002, subindex=0, value=value)])

    def syncs(self, since: float = 0.0) -> list:
        """Return the times SYNCs were recorded (after ``since``)."""
        return [stamp for stamp, message in list(self.recorder.frames)
                if message.arbitration_id == SYNC and stamp > since]

    def sync_arrivals(self, since: float = 0.0) -> list:
        """Return the kernel's arrival times of the SYNCs recorded after ``since``.

        The socket's own stamps: a recording thread held up by this busy process does not
        make SYNCs that came in time look late.
        """
        return [message.timestamp for stamp, message in list(self.recorder.frames)
                if message.arbitration_id == SYNC and stamp > since]

    def frame_of(self, value: int) -> int:
        """Wait for the RPDO 2 frame carrying ``value``; return its place in the recording."""
        def found():
            return next((number + 1 for number, (_, message) in enumerate(
                list(self.recorder.frames)) if message.arbitration_id == 0x300 + NODE
                and bytes(message.data[:4]) == value.to_bytes(4, 'little')), None)
        return wait_until(found, ANSWER, f'the frame of {value} recorded') - 1

    def syncs_before_frame_of(self, value: int, since: float) -> list:
        """Return when the SYNCs recorded after ``since`` and before ``value``'s frame came."""
        at = self.frame_of(value)
        return [stamp for stamp, message in list(self.recorder.frames)[:at]
                if message.arbitration_id == SYNC and stamp > since]

    def close(self) -> None:
        """Stop recording."""
        self.recorder.close()


def _gaps(stamps: list) -> list:
    return [later - earlier for earlier, later in zip(stamps, stamps[1:], strict=False)]


def test_the_sync_counter_runs_on_unbroken_across_a_stall_of_the_node(start_node, client_node,
                                                                       start_durand):
    # The node stops (SIGSTOP: a pause of the process) for a few SYNC periods. The SYNCs it
    # missed are skipped, not sent late: the counter of the SYNCs that do go out goes on by
    # one, from where it was, and no two SYNCs come back to back.
    period, overflow = 0.2, 4
    rig = Rig(start_node, client_node, start_durand, '-p', f'sync.period:={period}',
              '-p', f'sync.counter_overflow:={overflow}')
    try:
        wait_until(lambda: len(rig.syncs()) >= 3, ANSWER, 'SYNCs')
        stopped = time.monotonic()
        rig.node.process.send_signal(signal.SIGSTOP)
        try:
            threading.Event().wait(3.7 * period)
        finally:
            rig.node.process.send_signal(signal.SIGCONT)
        wait_until(lambda: len(rig.syncs(stopped)) >= 6, ANSWER, 'SYNCs after the stall')
        counters = [message.data[0] for _, message in list(rig.recorder.frames)
                    if message.arbitration_id == SYNC]
        assert all(later == earlier % overflow + 1
                   for earlier, later in zip(counters, counters[1:], strict=False)), counters
        gaps = _gaps(rig.syncs(stopped - 2 * period))
        assert min(gaps) > 0.4 * period, gaps
    finally:
        rig.close()


def test_cleanup_ends_sync_and_configure_again_starts_one_producer(start_node, client_node,
                                                                     start_durand):
    # The managed node: SYNC from configure until cleanup, none after cleanup answered, and
    # after configure again one SYNC producer, at the period (not two, at twice the rate).
    period = 0.1
    rig = Rig(start_node, client_node, start_durand, '-p', f'sync.period:={period}',
              program='cbcan_lifecycle_node')
    change = service_client(client_node, ChangeState, f'{rig.name}/change_state', rig.node)

    def transition(transition_id: int) -> float:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        assert call(change, request, f'transition {transition_id}', rig.node, ANSWER).success
        return time.monotonic()

    try:
        for _ in range(2):
            configured = transition(Transition.TRANSITION_CONFIGURE)
            transition(Transition.TRANSITION_ACTIVATE)
            rig.wait_written()
            wait_until(lambda c=configured: len(rig.syncs(c)) >= 3, ANSWER, 'SYNCs')
            window = time.monotonic()
            wait_until(lambda w=window: time.monotonic() > w + 20 * period, ANSWER, 'a while')
            count = len([s for s in rig.syncs(window) if s < window + 20 * period])
            assert 10 <= count <= 22, f'{count} SYNCs in 20 periods'
            transition(Transition.TRANSITION_DEACTIVATE)
            cleaned = transition(Transition.TRANSITION_CLEANUP)
            answered = time.time()  # the socket stamps frames on the wall clock
            wait_until(lambda: not rig.pdo_write.service_is_ready(), ANSWER,
                       'pdo_write taken away by cleanup')
            wait_until(lambda c=cleaned: time.monotonic() > c + 10 * period, ANSWER, 'a while')
            after = [stamp for stamp in rig.sync_arrivals(cleaned - 5.0) if stamp > answered]
            assert not after, f'{len(after)} SYNCs after cleanup was answered'
    finally:
        rig.close()


def test_a_synchronous_write_goes_out_after_a_sync_that_came_after_the_call(
        start_node, client_node, start_durand):
    # pdo_write on a synchronous RPDO: the frame goes out right after the next SYNC, never
    # before a SYNC that followed the call; called at every phase of the cycle.
    period = 0.05
    rig = Rig(start_node, client_node, start_durand, '-p', f'sync.period:={period}')
    try:
        for number in range(20):
            threading.Event().wait(period * 0.37)
            called = time.monotonic()
            value = 1000 + number
            answer = call(rig.pdo_write, rig.request(float(value)), 'pdo_write', rig.node,
                          ANSWER)
            assert answer.success, answer.message
            assert rig.syncs_before_frame_of(value, called), (
                f'write {number}: its frame went out before any SYNC after the call')
    finally:
        rig.close()


def test_a_synchronous_write_waiting_through_a_stall_goes_out_after_a_sync(
        start_node, client_node, start_durand):
    # The node stops (SIGSTOP: a pause of the process) while a synchronous write waits for
    # its SYNC, and runs again past half a period after the SYNC it missed, which is then
    # skipped: the write still goes out after a SYNC (the next one sent), as pdo_write says.
    period = 1.0
    rig = Rig(start_node, client_node, start_durand, '-p', f'sync.period:={period}')
    try:
        for value in range(100, 104):
            count = len(rig.syncs())
            wait_until(lambda c=count: len(rig.syncs()) > c, ANSWER, 'a SYNC')
            sync = rig.syncs()[-1]
            called = time.monotonic()
            if called > sync + 0.2 * period:
                continue  # the recording came late: try again at the next SYNC
            written = rig.pdo_write.call_async(rig.request(float(value)))
            wait_until(lambda s=sync: time.monotonic() > s + 0.5 * period, ANSWER, 'mid-cycle')
            if rig.syncs(sync):
                continue  # (a late recording)
            rig.node.process.send_signal(signal.SIGSTOP)
            try:
                wait_until(lambda s=sync: time.monotonic() > s + 1.75 * period, ANSWER,
                           'past half the next cycle')
            finally:
                rig.node.process.send_signal(signal.SIGCONT)
            answer = wait_for_future(written, ANSWER)
            assert answer.success, answer.message
            assert rig.syncs_before_frame_of(value, called), (
                'the write went out with no SYNC after the call before it')
            return
        raise AssertionError('the recording was late at every SYNC')
    finally:
        rig.close()
