"""Attacks on boot configuration: races, contradictions and faults a robot meets.

Each test names a promise of docs/boot_configuration.md and the way it was broken. Races are
made certain, not likely: the boot service runs on fakes of its collaborators whose calls
are the moments that matter (an NMT start going out, a listener being told of a change).
"""

from concurrent.futures import Future
from dataclasses import replace
import threading
import time

import pytest
from test_boot_configuration import (  # noqa: F401 - rig is a fixture
    bus_file,
    CONFIGURED,
    downloads,
    EDS,
    NODE,
    rig,
    starts,
    state_of,
    WAIT,
    wait_for_boot,
)

from cbcan_ros.core import nmt
from cbcan_ros.core.boot.plan import BootSettings, DevicePlan
from cbcan_ros.core.boot.service import BootService
from cbcan_ros.core.bus import BusStatus
from cbcan_ros.core.gateway import NmtResult
from cbcan_ros.core.nmt import NodeStatus
from cbcan_ros.core.sdo.request_queue import Deadlines
from cbcan_ros.core.sdo.requests import SdoResult
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import new_channel, wait_until
import faulty_bus
from faulty_bus import FaultController

faulty_bus.register()


class FakeNetwork:
    """The network as the boot service sees it: frames are delivered by the test."""

    def __init__(self):
        self.handlers = {}

    def subscribe(self, cob_id, handler):
        """Take a frame handler."""
        self.handlers[cob_id] = handler

    def unsubscribe(self, cob_id, handler):
        """Drop a frame handler."""
        self.handlers.pop(cob_id, None)

    def boot_up(self, node_id: int) -> None:
        """Deliver node_id's boot-up message, as the receive thread would."""
        self.handlers[nmt.HEARTBEAT_COB_BASE + node_id](
            nmt.HEARTBEAT_COB_BASE + node_id, bytearray([nmt.BOOT_UP]), time.monotonic())


class FakeMonitor:
    """A heartbeat monitor that never loses a device."""

    def add_listener(self, listener):
        """Take a listener never called."""


class FakePdo:
    """A PDO service (plans here have no PDOs served unless a test says so)."""

    def read_again(self, node_id):
        """Read a mapping: never answered."""
        return Future()


class FakeDevices:
    """SDO and NMT of devices that answer every read of 0x1000 at once, unless gated."""

    def __init__(self):
        self.lock = threading.Lock()
        self.reads = []         # node ids, one per 0x1000 read
        self.commands = []      # (node_id, command) sent
        self.gates = {}         # node_id: Event a read of it waits for
        self.on_command = None  # called with (node_id, command) as a command goes out
        self.on_read = threading.Condition(self.lock)

    def sdo_batch(self, accesses, timeout, stop):
        """Answer each read with a device type, waiting at a node's gate when it has one."""
        results = []
        for access in accesses:
            gate = self.gates.get(access.node_id)
            if gate is not None:
                gate.wait(WAIT)
            if stop(results):
                break
            with self.lock:
                self.reads.append(access.node_id)
                self.on_read.notify_all()
            results.append(SdoResult.ok(b'\x92\x01\x02\x00'))
        results += [SdoResult(False, message='not sent')] * (len(accesses) - len(results))
        future = Future()
        future.set_result(results)
        return future

    def nmt_command(self, node_id, command):
        """Record a command, calling ``on_command`` as it goes out."""
        with self.lock:
            self.commands.append((node_id, command))
        if self.on_command is not None:
            self.on_command(node_id, command)
        return NmtResult(True)

    def reads_of(self, node_id):
        """Return how often node_id's 0x1000 was read."""
        with self.lock:
            return self.reads.count(node_id)


def plain_plan(node_id, mandatory=False):
    """Return a device checked by its 0x1000 only: one SDO read per boot, no reset, started."""
    return DevicePlan(node_id=node_id, name=f'node_{node_id}', heartbeat_check=False,
                      reset_communication=False, mandatory=mandatory)


def boot_service(plans, devices, network):
    deadlines = Deadlines()
    service = BootService(network, BootSettings(plans=tuple(plans), boot_timeout=1.0),
                          devices.sdo_batch, devices.nmt_command, FakePdo(), FakeMonitor(),
                          deadlines, 0.5)
    return service, deadlines


def state(service, node_id):
    return next(s for s in service.states() if s.node_id == node_id)


def test_a_device_held_for_a_mandatory_one_is_not_started_after_its_own_next_boot_up():
    """Promises 1 and 2: the held device's next boot-up comes as the mandatory one is started.

    The start of the held device must not go out for its new boot (that boot has not even
    read 0x1000 yet), nor may it be shown BOOTED while that boot runs.
    """
    devices, network = FakeDevices(), FakeNetwork()
    mandatory, held = 1, 2
    devices.gates[mandatory] = threading.Event()
    service, deadlines = boot_service([plain_plan(mandatory, True), plain_plan(held)],
                                      devices, network)
    second_boot = threading.Event()

    def boot_up_of_the_held_device(node_id, command):
        if (node_id, command) == (mandatory, nmt.START):
            devices.gates[held] = second_boot  # its new boot waits in its first read
            network.boot_up(held)
    devices.on_command = boot_up_of_the_held_device
    service.start()
    try:
        wait_until(lambda: state(service, held).state == 'WAITING'
                   and 'mandatory' in state(service, held).message, WAIT, 'node 2 held')
        devices.gates[mandatory].set()
        wait_until(lambda: state(service, mandatory).state == 'BOOTED', WAIT, 'node 1 booted')
        wait_until(lambda: state(service, held).state in ('BOOTING', 'BOOTED'), WAIT,
                   'node 2 booting again')
        assert (held, nmt.START) not in devices.commands, (
            'node 2 was started for a boot that has not read its 0x1000 yet')
        assert state(service, held).state == 'BOOTING', state(service, held)
        second_boot.set()
        wait_until(lambda: state(service, held).state == 'BOOTED', WAIT, 'node 2 booted')
    finally:
        second_boot.set()
        service.stop()
        deadlines.stop()


def test_a_device_another_boot_thread_starts_is_not_booted_twice():
    """Promise 7: two devices ending their boots at once: each is booted once, not again.

    Node 3's boot ends while node 2's thread tells its listeners node 2 booted; node 3's
    thread then starts node 2 too. Node 2's own thread must not take that as a boot still
    to do (a second reset and configuration of a device just started).
    """
    devices, network = FakeDevices(), FakeNetwork()
    first, second = 2, 3
    devices.gates[second] = threading.Event()
    service, deadlines = boot_service([plain_plan(first), plain_plan(second)], devices,
                                      network)
    taken = threading.Event()

    def when_node_2_is_ready():
        # Node 2's thread telling of its verified boot: let node 3's boot end now, and wait
        # until node 3's thread is starting node 2.
        if (threading.current_thread().name == f'boot-{first}'
                and state(service, first).state == 'BOOTING'
                and devices.reads_of(first) == 1 and not taken.is_set()):
            devices.gates[second].set()
            taken.wait(WAIT)

    def start_of_node_2_from_node_3s_thread(node_id, command):
        if (node_id, command) == (first, nmt.START) and \
                threading.current_thread().name == f'boot-{second}':
            taken.set()
            with devices.on_read:  # what node 2's own thread does meanwhile
                devices.on_read.wait_for(lambda: devices.reads.count(first) > 1, 1.0)
    service.add_listener(when_node_2_is_ready)
    devices.on_command = start_of_node_2_from_node_3s_thread
    service.start()
    try:
        for node_id in (first, second):
            wait_until(lambda n=node_id: state(service, n).state == 'BOOTED', WAIT,
                       f'node {node_id} booted')
        assert taken.is_set(), 'the race was not set up: node 3 did not start node 2'
        assert devices.reads_of(first) == 1, (
            f'node 2 was booted {devices.reads_of(first)} times: {devices.commands}')
    finally:
        devices.gates[second].set()
        service.stop()
        deadlines.stop()


def test_a_mandatory_device_left_alone_does_not_hold_the_others(rig):  # noqa: F811
    """Promise 2: ``mandatory`` in defaults and one node ``boot: false`` (left alone).

    Lely boots no such node and counts it as booted (0x1F81 bit 2 clear); here it held every
    other device unstarted for ever, 'waiting' for a boot that is never run.
    """
    text = CONFIGURED.replace('nodes:\n', 'defaults:\n  mandatory: true\nnodes:\n') + (
        '  spare:\n    node_id: 11\n    dcf: device.eds\n    boot: false\n')
    gateway, devices, frames = rig(text, node_ids=(NODE, 11))
    assert state_of(gateway, 11).state == 'IGNORED'
    state = wait_until(lambda: state_of(gateway, NODE).boots >= 1 and state_of(gateway, NODE),
                       WAIT, 'node 10 boot ended')
    assert state.state == 'BOOTED' and 'started' in state.message, state
    wait_until(lambda: starts(frames.snapshot()), WAIT, 'node 10 started')


SILENT = CONFIGURED.replace('heartbeat_producer: 100', 'heartbeat_producer: 0').replace(
    'boot_timeout: 1000', 'boot_timeout: 4000')
SDO_ANSWER, HEARTBEAT = 0x580 + NODE, 0x700 + NODE


@pytest.fixture
def faulty_rig(make_gateway, tmp_path):
    """Start a durand device and a gateway on the faulty interface of one channel."""
    made = []

    def start(text: str = SILENT):
        channel = new_channel()
        device = DurandDevice(NODE, channel=channel)
        device.start()
        made.append((channel, device))
        gateway = make_gateway(can__interface='faulty', can__channel=channel,
                               simulation__devices=None, bus_config=bus_file(tmp_path, text))
        return gateway, device, FaultController.get(channel)

    yield start
    for channel, device in made:
        device.stop()
        FaultController.forget(channel)


def bus_down_and_up(gateway, faults) -> None:
    faults.fail_receive('adapter unplugged')
    wait_until(lambda: not gateway.node.gateway.bus_status.up, WAIT, 'the bus down')
    faults.clear()
    wait_until(lambda: gateway.node.gateway.bus_status.up, 30.0, 'the bus up again')


def test_a_silent_device_whose_boot_the_bus_ended_is_booted_when_the_bus_is_back(faulty_rig):
    """Promise 7: the bus goes down mid-boot, then up; the device sends no heartbeat.

    The gateway knows its boot did not end; it must boot it again once the bus is back,
    not wait for ever for a heartbeat (the configuration switches it off).
    """
    gateway, device, faults = faulty_rig()
    # Not answering yet, nor beating: the boot waits for its boot-up, then asks 0x1000
    # again and again (boot_timeout).
    device._network.allowed = lambda cob_id: cob_id not in (SDO_ANSWER, HEARTBEAT)
    wait_until(lambda: state_of(gateway).state == 'BOOTING', WAIT, 'the boot under way')
    faults.fail_receive('adapter unplugged')
    wait_until(lambda: state_of(gateway).state == 'WAITING', WAIT, 'the boot ended')
    device._network.allowed = lambda cob_id: cob_id != HEARTBEAT  # answers now
    faults.clear()
    wait_until(lambda: gateway.node.gateway.bus_status.up, 30.0, 'the bus up again')
    try:
        state = wait_for_boot(gateway, 'BOOTED')
    except AssertionError as stuck:
        raise AssertionError(f'not booted again after the bus came back: {stuck}') from None
    assert 'started' in state.message, state


def test_the_bus_going_down_while_the_pdo_mapping_is_read_ends_the_boot_without_a_verdict():
    """Promises 1 and 3: a bus down is no failure of the device (no J), and it boots after.

    The bus goes down as the boot reads the device's PDO mapping again (step 5); the
    gateway tells the boot service first, then the read fails, as gateway.py does.
    """
    devices, network = FakeDevices(), FakeNetwork()
    service, deadlines = boot_service([replace(plain_plan(NODE), pdos=True)], devices,
                                      network)
    down = BusStatus(False, 'adapter unplugged', 0, 0, 0, 0)
    reads = []

    class BusGoesDownAtTheFirstRead(FakePdo):
        def read_again(self, node_id):
            """Fail the first read: the bus went down."""
            reads.append(node_id)
            future = Future()
            if len(reads) == 1:
                service.on_bus_change(down)
                future.set_result(f'PDO mapping not read: 0x1A00:1: the CAN bus is down: '
                                  f'{down.reason}')
            else:
                future.set_result('')
            return future
    service._pdo = BusGoesDownAtTheFirstRead()
    service.start()
    try:
        ended = wait_until(lambda: (state(service, NODE).state == 'FAILED'
                                    or 'ended' in state(service, NODE).message)
                           and state(service, NODE), WAIT, 'the boot ended')
        assert ended.state == 'WAITING' and ended.error_status == '', (
            f'the bus going down was taken for a failure of the device: {ended}')
        service.on_bus_change(replace(down, up=True, reason=''))
        wait_until(lambda: state(service, NODE).state == 'BOOTED', WAIT, 'booted again')
    finally:
        service.stop()
        deadlines.stop()


def test_a_dcf_mapping_without_its_cob_id_is_written_with_the_pdo_disabled(rig, tmp_path):  # noqa: F811, E501
    """CiA 301 order: a DCF giving RPDO 1's mapping (ParameterValue) but not its COB-ID.

    The mapping must still be written with the PDO disabled (bit 31 of its COB-ID first,
    valid again after); a real device refuses a mapping changed while its PDO is valid.
    """
    text = CONFIGURED.replace('dcf: device.eds', 'dcf: mapped.dcf')
    # The first mapping record of the file is RPDO 1's (0x1600).
    (tmp_path / 'mapped.dcf').write_text(EDS.read_text().replace(
        'DataType=0x0005\nAccessType=rw\nDefaultValue=2\nPDOMapping=0\n',
        'DataType=0x0005\nAccessType=rw\nDefaultValue=2\nPDOMapping=0\nParameterValue=1\n',
        1))
    gateway, devices, frames = rig(text)
    wait_for_boot(gateway, 'BOOTED')
    written = [obj for _, obj in downloads(frames.snapshot())]
    mapping = [position for position, obj in enumerate(written) if obj[0] == 0x1600]
    disabled = [position for position, obj in enumerate(written) if obj == (0x1400, 1)]
    assert mapping, written
    assert disabled and disabled[0] < mapping[0] < mapping[-1] < disabled[-1], (
        f'RPDO 1 mapping written while the PDO is valid: '
        f'{[f"0x{index:04X}:{sub}" for index, sub in written]}')


@pytest.mark.parametrize('endless', [float('inf'), float('nan'), -1.0, 1e10])
def test_a_boot_call_with_an_endless_timeout_is_refused_and_others_keep_their_deadlines(  # noqa: E501
        rig, endless):  # noqa: F811
    """Promise 5: ``~/boot`` with timeout inf, NaN, below 0 or past an hour is refused at once.

    Its deadline went into the gateway's one deadline thread unchecked: inf raised
    OverflowError there (the thread ended), NaN stayed at the top of its heap for good (no
    later deadline fired, the thread spun); either way no later call was timed out again.
    1e10 s, past what a thread can wait, ended the thread too (a red team).
    """
    text = CONFIGURED.replace('boot_timeout: 1000', 'boot_timeout: 20000') + (
        '  absent:\n    node_id: 11\n    dcf: device.eds\n')
    gateway, devices, frames = rig(text)
    wait_for_boot(gateway, 'BOOTED')
    refused = gateway.call('boot', node_id=NODE, timeout=endless)
    assert not refused.success and 'timeout' in refused.message, refused.message
    answer = gateway.call('boot', node_id=11, timeout=0.5, wait=10.0)
    assert not answer.success and 'still booting' in answer.message, answer.message


class SilentMonitor:
    """A heartbeat monitor that finds every device silent when its listener is called."""

    def __init__(self):
        self.listeners = []

    def add_listener(self, listener):
        """Keep the listener, called by the test."""
        self.listeners.append(listener)

    def status(self, node_id):
        """Every device is not detected."""
        return NodeStatus(node_id, nmt.NOT_DETECTED, None, -1.0, detected=False)


def test_a_device_silent_during_its_own_boot_is_not_booted_again_by_its_first_heartbeat():
    # A device whose factory 0x1017 is 0 sends nothing between its boot-up and the write of
    # its heartbeat time: a boot longer than heartbeat.timeout made the monitor lose it, and
    # its first heartbeat then started the boot again, which reset it to silence again.
    devices, network, monitor = FakeDevices(), FakeNetwork(), SilentMonitor()
    gate = devices.gates[2] = threading.Event()
    service = BootService(network, BootSettings(plans=(plain_plan(2),), boot_timeout=1.0),
                          devices.sdo_batch, devices.nmt_command, FakePdo(), monitor,
                          Deadlines(), 0.5)
    service.start()
    try:
        network.boot_up(2)  # heard: its boot runs, waiting at the gate
        for listener in monitor.listeners:
            listener()  # silent for heartbeat.timeout while its boot runs
        gate.set()
        wait_until(lambda: state(service, 2).state == 'BOOTED', WAIT, 'node 2 booted')
        asked = service._devices[2].wanted
        network.handlers[nmt.HEARTBEAT_COB_BASE + 2](
            nmt.HEARTBEAT_COB_BASE + 2, bytearray([nmt.OPERATIONAL]), time.monotonic())
        # The heartbeat handler asks for a boot there and then, or never.
        assert service._devices[2].wanted == asked, 'its first heartbeat booted it again'
        assert state(service, 2).boots == 1, state(service, 2)
    finally:
        service.stop()


class DriveWithoutVelocityTarget(FakeDevices):
    """A position-only drive: 0x60FF does not exist; every other access succeeds."""

    def __init__(self):
        super().__init__()
        self.written = []

    def sdo_batch(self, accesses, timeout, stop):
        """Answer as the gateway's channel does: nothing sent once ``stop`` says so."""
        results = []
        for access in accesses:
            if stop(results):
                results.append(SdoResult(False, message='not sent'))
            elif access.index == 0x60FF:
                results.append(SdoResult.aborted(0x06020000))
            else:
                if access.write:
                    self.written.append(access.index)
                results.append(SdoResult.ok(b'\x92\x01\x02\x00'))
        future = Future()
        future.set_result(results)
        return future


def test_a_drive_without_one_of_the_targets_gets_the_others_set_safe_and_boots():
    devices, network = DriveWithoutVelocityTarget(), FakeNetwork()
    plan = replace(plain_plan(2), drive=True)
    service, deadlines = boot_service([plan], devices, network)
    service.start()
    try:
        wait_until(lambda: state(service, 2).state in ('BOOTED', 'FAILED'), WAIT,
                   'the boot ended')
        assert state(service, 2).state == 'BOOTED', state(service, 2)
        assert devices.written == [0x607A, 0x6071]  # target position = actual, torque 0
    finally:
        service.stop()
        deadlines.stop()
