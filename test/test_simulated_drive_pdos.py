"""The simulated CiA 402 drive's PDOs, as the gateway serves them (``simulation.drives``).

A drive of ``simulation.drives`` comes with the PDO mapping of ``default_drive_pdos``; the
gateway reads it like any device's, publishes what the drive sends on ``~/node_<id>/rpdo``
and moves the drive with ``~/pdo_write``, as its drive support will. Synchronous variants of
the same mapping act at SYNC. Conditions are waited for with generous ceilings, never proved
by sleeping; what must not happen before a SYNC is proved by frames sent in order.
"""

import struct
import sys

import can
import pytest
from test_pdo_topics import Recorder, values

from cbcan_ros.msg import PdoEntry
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_pdos import (
    COMMAND,
    default_drive_pdos,
    MOTION,
    SET_POINTS,
    STATUS,
)
from cbcan_ros.simulation.durand.pdos import PdoConfig
from cbcan_ros.simulation.simulated_drives import simulated_drives

from conftest import wait_until

DRIVE = 6
WAIT = 15.0  # seconds: a ceiling for what takes a few ticks on a quiet machine
SYNC_PERIOD = 0.02

STATUSWORD, MODE_DISPLAY, POSITION, VELOCITY = (0x6041, 0), (0x6061, 0), (0x6064, 0), (0x606C, 0)
SHUTDOWN, SWITCH_ON, ENABLE, NEW_SET_POINT = 0x06, 0x07, 0x0F, 0x10
PP, CSV = 1, 9  # modes of operation
BITS = {0x6040: 16, 0x6041: 16, 0x6060: 8, 0x6061: 8, 0x6064: 32, 0x606C: 32, 0x6071: 16,
        0x6077: 16, 0x607A: 32, 0x60FF: 32}


def shows_enabled(statusword: float) -> bool:
    """Return whether a statusword shows OPERATION_ENABLED (mask 0x6F, value 0x27)."""
    return int(statusword) & 0x6F == 0x27


@pytest.fixture
def served(make_gateway):
    """Return (gateway, drive, recorder): a drive of simulation.drives, its PDOs served."""
    gateway = make_gateway(simulation__devices=None, simulation__drives=[DRIVE],
                           nodes=[DRIVE], pdo__nodes=[DRIVE])
    recorder = Recorder(gateway.client_node, DRIVE)
    drive = gateway.device(DRIVE)
    assert isinstance(drive, DurandDrive)
    wait_until(lambda: gateway.node.gateway.pdo.mappings(DRIVE)[0], WAIT,
               'the PDO mapping of the drive read')
    return gateway, drive, recorder


def start(gateway, node_id: int = DRIVE) -> None:
    """Start the drive's PDOs (NMT start) and wait until the gateway sees it OPERATIONAL."""
    assert gateway.call('nmt_command', node_id=node_id, command=1).success
    gateway.wait_for_states({node_id: 'OPERATIONAL'}, WAIT)


def write(gateway, pdo: int, node_id: int = DRIVE, **objects) -> None:
    """Send RPDO ``pdo`` with values by object (``controlword=6``); it must go out."""
    indexes = {'controlword': 0x6040, 'target_position': 0x607A, 'mode': 0x6060,
               'target_velocity': 0x60FF, 'target_torque': 0x6071}
    answer = gateway.call('pdo_write', node_id=node_id, pdo=pdo, entries=[
        PdoEntry(index=indexes[name], subindex=0, value=float(value))
        for name, value in objects.items()])
    assert answer.success, answer.message


def wait_for_pdo(recorder: Recorder, pdo: int, condition, what: str) -> dict:
    """Wait until a message of TPDO ``pdo`` has values meeting ``condition``; return them."""
    def found():
        return next((values(message) for message in recorder.of(pdo)
                     if condition(values(message))), None)
    return wait_until(found, WAIT, f'{what} in TPDO {pdo}')


def enable(gateway, recorder: Recorder, mode: int) -> None:
    """Bring the drive to OPERATION_ENABLED in ``mode`` by RPDO 1 alone, seen in TPDO 1."""
    for controlword in (SHUTDOWN, SWITCH_ON, ENABLE):
        write(gateway, 1, controlword=controlword, mode=mode)
    wait_for_pdo(recorder, 1, lambda seen: shows_enabled(seen[STATUSWORD])
                 and seen[MODE_DISPLAY] == mode, 'OPERATION_ENABLED')


def test_the_gateway_reads_the_default_mapping(served):
    gateway, drive, _ = served
    tpdos, rpdos = gateway.node.gateway.pdo.mappings(DRIVE)
    read = {('tpdo', number): mapping for number, mapping in tpdos.items()}
    read.update({('rpdo', number): mapping for number, mapping in rpdos.items()})
    for config in default_drive_pdos():
        mapping = read[(config.kind, config.number)]
        assert mapping.enabled == config.enabled, mapping
        if not config.enabled:
            continue
        assert mapping.transmission_type == config.transmission_type, mapping
        assert mapping.event_timer == config.event_timer, mapping
        assert [(entry.index, entry.subindex, entry.bits) for entry in mapping.entries] == [
            (index, subindex, BITS[index]) for index, subindex in config.mapping], mapping
        assert not mapping.problem, mapping
    assert [config.mapping for config in default_drive_pdos() if config.enabled] == [
        STATUS, MOTION, COMMAND, SET_POINTS]


def test_controlword_in_rpdo1_enables_the_drive_and_tpdo1_shows_it(served):
    gateway, drive, recorder = served
    start(gateway)
    first = wait_for_pdo(recorder, 1, lambda seen: True, 'the statusword')
    assert int(first[STATUSWORD]) & 0x4F == 0x40, 'SWITCH_ON_DISABLED after boot'
    enable(gateway, recorder, CSV)
    assert drive.drive_state == 'OPERATION_ENABLED'


def test_position_and_velocity_arrive_in_tpdo2(served):
    gateway, drive, recorder = served
    start(gateway)
    enable(gateway, recorder, CSV)
    write(gateway, 2, target_velocity=2000, target_torque=0)
    moving = wait_for_pdo(recorder, 2, lambda seen: seen[VELOCITY] == 2000, 'velocity 2000')
    later = wait_for_pdo(recorder, 2, lambda seen: seen[POSITION] > moving[POSITION] + 100,
                         'the position growing')
    assert later[VELOCITY] == 2000
    # Event-timer driven: they keep coming while nothing is written.
    seen = len(recorder.of(2))
    wait_until(lambda: len(recorder.of(2)) >= seen + 20, WAIT, '20 more TPDO 2 frames')


def test_a_new_set_point_takes_the_target_position_of_the_same_frame(served):
    # The controlword is mapped before the target position: a drive takes the frame whole.
    gateway, drive, recorder = served
    start(gateway)
    enable(gateway, recorder, PP)
    write(gateway, 1, controlword=ENABLE | NEW_SET_POINT, target_position=3000, mode=PP)
    wait_for_pdo(recorder, 2, lambda seen: seen[POSITION] == 3000, 'position 3000')
    assert drive.position == 3000


@pytest.fixture
def sync_rig(make_gateway, start_durand):
    """Return a factory ``sync_rig(sync_period, pdos)``: (gateway, drive, recorder, raw bus)."""
    buses = []

    def factory(sync_period: float, pdos):
        gateway = make_gateway(simulation__devices=None, nodes=[DRIVE], pdo__nodes=[DRIVE],
                               sync__period=sync_period)
        recorder = Recorder(gateway.client_node, DRIVE)
        drive = start_durand(DRIVE, kind=DurandDrive, channel=gateway.channel, pdos=pdos)
        bus = gateway.raw_bus()
        buses.append(bus)
        wait_until(lambda: gateway.node.gateway.pdo.mappings(DRIVE)[0], WAIT,
                   'the PDO mapping of the drive read')
        return gateway, drive, recorder, bus

    yield factory
    for bus in buses:
        bus.shutdown()


def test_synchronous_rpdo1_enables_the_drive_sync_by_sync(sync_rig):
    gateway, drive, recorder, _ = sync_rig(SYNC_PERIOD, default_drive_pdos(1))
    start(gateway)
    # Each write goes out after a SYNC and is applied at the next: one step per SYNC, as a
    # synchronous RPDO applies only the last frame received before a SYNC.
    enable(gateway, recorder, CSV)
    write(gateway, 2, target_velocity=500, target_torque=0)
    wait_for_pdo(recorder, 2, lambda seen: seen[VELOCITY] == 500, 'velocity 500')


def send(bus: can.BusABC, cob_id: int, data: bytes = b'') -> None:
    bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))


def sdo_round_trip(gateway) -> None:
    """Read the drive's statusword by SDO: every frame sent before is handled by then."""
    assert gateway.call('sdo_read', node_id=DRIVE, index=0x6041, subindex=0).success


def test_a_synchronous_rpdo_waits_for_the_sync(sync_rig):
    gateway, drive, _, bus = sync_rig(0.0, default_drive_pdos(1))  # SYNC only from the test
    start(gateway)
    for controlword in (SHUTDOWN, SWITCH_ON, ENABLE):
        send(bus, 0x200 + DRIVE, struct.pack('<Hib', controlword, 0, CSV))
        sdo_round_trip(gateway)
        before = drive.drive_state
        send(bus, 0x80)
        sdo_round_trip(gateway)
        after = drive.drive_state
        assert before != after, f'controlword 0x{controlword:02X} not applied at the SYNC'
        assert drive.statusword & 0x6F == {SHUTDOWN: 0x21, SWITCH_ON: 0x23, ENABLE: 0x27}[
            controlword]
    assert drive.drive_state == 'OPERATION_ENABLED'


def test_synchronous_tpdos_go_out_every_nth_sync(sync_rig):
    # TPDO 1 every second SYNC, TPDO 2 every SYNC. Its handler runs after TPDO 1's, so when
    # TPDO 2 of a SYNC is in, TPDO 1 of that SYNC is too: counted, not timed.
    pdos = (PdoConfig('tpdo', 1, STATUS, 2), PdoConfig('tpdo', 2, MOTION, 1))
    gateway, drive, _, bus = sync_rig(0.0, pdos)
    start(gateway)
    frames = []
    for _ in range(12):
        send(bus, 0x80)
        while True:
            message = bus.recv(WAIT)
            assert message is not None, f'no TPDO 2 after a SYNC; frames {frames}'
            frames.append(message.arbitration_id)
            if message.arbitration_id == 0x280 + DRIVE:
                break
    assert frames.count(0x280 + DRIVE) == 12
    assert frames.count(0x180 + DRIVE) == 6, [hex(cob_id) for cob_id in frames]


def test_without_durand_the_drives_are_left_out_with_a_warning(monkeypatch):
    monkeypatch.setitem(sys.modules, 'durand', None)  # import durand fails
    for name in [name for name in sys.modules if name.startswith('cbcan_ros.simulation.')]:
        monkeypatch.delitem(sys.modules, name)  # imported again, without durand
    warnings = []
    assert simulated_drives([DRIVE], warnings.append, interface='virtual', channel='x') == []
    assert warnings == [f'parameter simulation.drives: drives [{DRIVE}] are not simulated: '
                        f'they need the Python package durand (pip install durand==0.5.0)']
