"""bus_config and the parameters: the file fills what is not given, a contradiction stops.

A ros2_canopen user brings a bus.yml; what it says of the master (heartbeat, SYNC), the
devices (lists, files, drivers) and the drives (joint names, scales) becomes the gateway's
parameters unless they are given; given otherwise, the node refuses to start naming both.
A value that cannot be written stops the start, naming the node and the key.
"""

import pathlib
import textwrap

import pytest
from rclpy.node import Node

from cbcan_ros.core import eds
from cbcan_ros.core.boot.description import load
from cbcan_ros.core.boot.plan import boot_settings, PlanError
from cbcan_ros.ros.config import NodeParameters
from cbcan_ros.ros.parameter_checks import ConfigurationError

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = ROOT / 'config' / 'simulated_device.eds'
DRIVE_EDS = ROOT / 'config' / 'cia402_drive.eds'

BUS = textwrap.dedent("""\
    master:
      node_id: 1
      heartbeat_producer: 50
      sync_period: 4000
    nodes:
      elbow:
        node_id: 4
        dcf: {drive}
        driver: ros2_canopen::Cia402Driver
        scale_pos_to_dev: 2000.0
        offset_pos_to_dev: 1000.0
        polling: true
      io:
        node_id: 6
        dcf: {eds}
        driver: ros2_canopen::ProxyDriver
    """)


def bus(tmp_path, text: str = BUS) -> str:
    """Write a bus file (``{drive}`` and ``{eds}`` put in); return its path."""
    path = tmp_path / 'bus.yml'
    path.write_text(text.format(drive=DRIVE_EDS, eds=EDS))
    return str(path)


def parameters(*given: str):
    """Return a node with the parameters ``name:=value`` given, and its NodeParameters."""
    node = Node('cbcan', cli_args=['--ros-args', *[part for name in given
                                                   for part in ('-p', name)]],
                use_global_arguments=False)
    return node, NodeParameters(node)


def test_the_bus_file_fills_every_parameter_not_given(tmp_path):
    node, given = parameters(f'bus_config:={bus(tmp_path)}')
    try:
        config = given.gateway_config()
        joints = given.joints()
    finally:
        node.destroy_node()
    assert (config.heartbeat_node_id, config.heartbeat_period) == (1, 0.05)
    assert config.sync_period == pytest.approx(0.004)
    assert config.expected_nodes == (4, 6) and config.drives.node_ids == (4,)
    assert config.pdo_nodes == (6,)
    assert config.device_files == {4: str(DRIVE_EDS), 6: str(EDS)}
    elbow = joints[4]
    assert (elbow.name, elbow.position_scale, elbow.velocity_scale) == ('elbow', 2000.0, 1000.0)
    assert elbow.position_offset == pytest.approx(-0.5)  # dev = pos * 2000 + 1000
    assert elbow.torque_scale == pytest.approx(1000.0)  # ros2_canopen's 0.001 from the device
    assert 'nodes.elbow.polling' in given.warnings[-1], given.warnings


def test_the_node_shows_the_values_the_bus_file_gives_as_its_parameters(tmp_path):
    # Red team: they were the gateway's only inside, so get_parameters showed node_4.eds
    # empty and cbcan_cli, which finds a node's EDS there, could not name its objects.
    node, _ = parameters(f'bus_config:={bus(tmp_path)}')
    try:
        shown = {name: node.get_parameter(name).value for name in (
            'heartbeat.node_id', 'heartbeat.period', 'sync.period', 'node_4.eds',
            'node_6.eds', 'node_4.joint', 'node_4.position_scale', 'node_4.position_offset')}
        lists = {name: list(node.get_parameter(name).value)
                 for name in ('nodes', 'drives.nodes', 'pdo.nodes')}
    finally:
        node.destroy_node()
    assert shown == {'heartbeat.node_id': 1, 'heartbeat.period': 0.05,
                     'sync.period': pytest.approx(0.004), 'node_4.eds': str(DRIVE_EDS),
                     'node_6.eds': str(EDS), 'node_4.joint': 'elbow',
                     'node_4.position_scale': 2000.0,
                     'node_4.position_offset': pytest.approx(-0.5)}
    assert lists == {'nodes': [4, 6], 'drives.nodes': [4], 'pdo.nodes': [6]}


def test_a_parameter_that_says_the_same_is_taken(tmp_path):
    node, given = parameters(f'bus_config:={bus(tmp_path)}', 'heartbeat.node_id:=1',
                             'node_4.position_scale:=2000.0')
    try:
        assert given.gateway_config().heartbeat_node_id == 1
    finally:
        node.destroy_node()


@pytest.mark.parametrize('parameter, key', [
    ('heartbeat.node_id:=5', 'master.node_id'),
    ('sync.period:=0.01', 'master.sync_period'),
    ('node_4.position_scale:=3.0', 'nodes.elbow.scale_pos_to_dev'),
    ('node_4.joint:=shoulder', 'nodes.elbow'),
])
def test_a_parameter_that_contradicts_the_bus_file_stops_the_start_naming_both(
        tmp_path, parameter, key):
    node, given = None, None
    try:
        with pytest.raises(ConfigurationError) as refused:
            node, given = parameters(f'bus_config:={bus(tmp_path)}', parameter)
            given.gateway_config()
            given.joints()
    finally:
        if node is not None:
            node.destroy_node()
    name = parameter.partition(':=')[0]
    assert f'parameter {name}' in str(refused.value) and key in str(refused.value), \
        str(refused.value)


def test_a_missing_bus_file_stops_the_start_naming_it(tmp_path):
    missing = str(tmp_path / 'nowhere.yml')
    with pytest.raises(ConfigurationError) as refused:
        parameters(f'bus_config:={missing}')
    assert 'parameter bus_config' in str(refused.value) and missing in str(refused.value)


def test_a_scale_back_that_is_not_the_inverse_is_refused(tmp_path):
    text = BUS.replace('scale_pos_to_dev: 2000.0', 'scale_pos_to_dev: 2000.0\n'
                       '    scale_pos_from_dev: 0.001')
    with pytest.raises(ConfigurationError) as refused:
        parameters(f'bus_config:={bus(tmp_path, text)}')
    assert 'scale_pos_from_dev' in str(refused.value) and '0.0005' in str(refused.value)


@pytest.mark.parametrize('entry, says', [
    ('{index: 0x2000, sub_index: 0, value: 300}', 'UNSIGNED8'),
    ('{index: 0x2003, sub_index: 0, value: 1.5}', 'no integer'),
    ('{index: 0x2021, sub_index: 0, value: 12}', 'no text'),
    ('{index: 0x2020, sub_index: 0, value: "0xZZ"}', 'no hex digits'),
    ('{index: 0x2999, sub_index: 0, value: 1}', 'not in the DCF'),
])
def test_a_value_that_cannot_be_written_stops_the_start_naming_node_and_key(
        tmp_path, entry, says):
    braced = entry.replace('{', '{{').replace('}', '}}')  # bus() formats the text
    text = BUS + f'    sdo:\n      - {braced}\n'
    description = load(bus(tmp_path, text))
    dictionaries = {4: eds.load(str(DRIVE_EDS), 4), 6: eds.load(str(EDS), 6)}
    with pytest.raises(PlanError) as refused:
        boot_settings(description, (), dictionaries, 1, lambda node_id: 300, (4,), (6,))
    assert 'nodes.io.sdo[1]' in str(refused.value) and says in str(refused.value), \
        str(refused.value)


def test_a_domain_value_comes_from_a_file_beside_the_bus_file(tmp_path):
    (tmp_path / 'table.bin').write_bytes(bytes(range(40)))
    text = BUS + '    sdo:\n      - {{index: 0x2020, sub_index: 0, value: "file:table.bin"}}\n'
    description = load(bus(tmp_path, text))
    settings = boot_settings(description, (), {4: eds.load(str(DRIVE_EDS), 4),
                                               6: eds.load(str(EDS), 6)},
                             1, lambda node_id: 300, (4,), (6,))
    io = next(plan for plan in settings.plans if plan.node_id == 6)
    assert [(w.index, w.data) for w in io.writes if w.source == 'sdo'] == [
        (0x2020, bytes(range(40)))]
