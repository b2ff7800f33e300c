"""At a signal, every powered drive of several gets its quick stop, though some fell silent.

Six drives on one bus, each enabled in CSV and streamed its target by a robot program; two
stop answering (their cable pulled) right before SIGINT. Each of the six gets the quick stop
download (0x2B 0x40 0x60 0x00 0x02 0x00 on 0x600 + id), the four alive take it and stand,
nothing commands a drive after its stop, and the node exits in time.
"""

import signal
import struct
import threading
from types import SimpleNamespace

import pytest
from std_msgs.msg import Float64
from test_drive_safety import (
    ANSWER,
    CONSUMER_TIME,
    CSV,
    is_download,
    layout_pdos,
    QUICK_STOP,
    Recorder,
    shown,
    standing_still,
    stop_with,
    Targets,
    VELOCITY,
)

from cbcan_ros.msg import DriveState
from cbcan_ros.ros.drives import STATE_QOS
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.srv import DriveCommand, NmtCommand

from conftest import wait_until
from node_process import arguments, call, namespace, private_bus, service_client, START_TIMEOUT

NODES = (2, 3, 4, 5, 6, 7)
SILENT = (3, 6)


def quick_stop_download(node_id: int):
    return lambda m: (m.arbitration_id == 0x600 + node_id
                      and bytes(m.data[:6]) == b'\x2b\x40\x60\x00' + struct.pack('<H',
                                                                                 QUICK_STOP))


def commands(node_id: int):
    rpdos = {base + node_id for base in (0x200, 0x300, 0x400, 0x500)}
    return lambda m: m.arbitration_id in rpdos or (is_download(m) and
                                                    m.arbitration_id == 0x600 + node_id)


@pytest.mark.parametrize('layout, sync', [
    ('combined', ()), ('vendor', ()), ('ros2_canopen', ('-p', 'sync.period:=0.01')),
    ('sdo_only', ())], ids=['combined', 'vendor', 'ros2_canopen-sync', 'sdo_only'])
def test_every_powered_drive_of_several_gets_its_stop_though_two_fell_silent(
        start_node, client_node, start_durand, layout, sync):
    group, port = private_bus()
    recorder = Recorder(group, port)
    drives, streams = {}, []
    try:
        for node_id in NODES:
            drives[node_id] = start_durand(node_id, kind=DurandDrive,
                                           interface='udp_multicast', channel=group,
                                           bus_options={'port': port},
                                           pdos=layout_pdos(layout))
        name = f'{namespace()}/cbcan'
        node = start_node(arguments(
            name, '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
            '-p', f'drives.nodes:={list(NODES)}', '-p', f'drives.consumer_time:={CONSUMER_TIME}',
            '-p', 'drives.command_timeout:=0.0', *sync), port)
        lock, states = threading.Lock(), {node_id: [] for node_id in NODES}

        def keep(node_id):
            def kept(message):
                with lock:
                    states[node_id].append(message.state)
            return kept
        for node_id in NODES:
            client_node.create_subscription(DriveState, f'{name}/node_{node_id}/drive_state',
                                            keep(node_id), STATE_QOS)
        wait_until(lambda: all('SWITCH_ON_DISABLED' in states[n] for n in NODES),
                   START_TIMEOUT, 'every drive read')
        nmt = service_client(client_node, NmtCommand, f'{name}/nmt_command', node)
        assert call(nmt, NmtCommand.Request(node_id=0, command=1), 'nmt start', node).success
        wait_until(lambda: all(d.state == 5 for d in drives.values()), ANSWER,
                   'every drive OPERATIONAL')
        command = service_client(client_node, DriveCommand, f'{name}/drive_command', node)
        for node_id in NODES:
            enabled = call(command, DriveCommand.Request(node_id=node_id, command='enable',
                                                         mode=CSV, timeout=10.0),
                           'enable', node, 25.0)
            assert enabled.success, enabled.message
            publisher = client_node.create_publisher(Float64,
                                                     f'{name}/node_{node_id}/target', 10)
            wait_until(lambda p=publisher: p.get_subscription_count() > 0, START_TIMEOUT,
                       'the node subscribed to the target')
            streams.append(Targets(publisher, VELOCITY))
        wait_until(lambda: all(d.velocity == VELOCITY for d in drives.values()), ANSWER,
                   'every drive moving')
        before = recorder.mark()
        for node_id in SILENT:
            drives[node_id].stop()
        stop_with(SimpleNamespace(node=node), signal.SIGINT)
        for targets in streams:
            targets.stop()
        recorder.mark()
        messages = recorder.messages(before)
        for node_id in NODES:
            stops = [number for number, m in enumerate(messages)
                     if quick_stop_download(node_id)(m)]
            assert stops, (f'drive {node_id} ({"silent" if node_id in SILENT else "alive"}) '
                           f'got no quick stop; frames to it: '
                           f'{shown([m for m in messages if commands(node_id)(m)])}\n'
                           f'{node.output()[-3000:]}')
            after = [m for m in messages[stops[0] + 1:] if commands(node_id)(m)]
            assert not after, f'frames commanding drive {node_id} after its stop: {shown(after)}'
        for node_id in set(NODES) - set(SILENT):
            wait_until(lambda n=node_id: standing_still(drives[n]), ANSWER,
                       f'drive {node_id} stopped')
    finally:
        for targets in streams:
            targets.stop()
        recorder.close()
