"""Parameters at start: every wrong value stops the node with one message; the examples load.

Each bad value is given as a user gives it (``-p name:=value`` or a parameter file, parsed by
rcl) and must be refused with one message naming the parameter, the value and what is
allowed. Every case runs in this process (a node built from those arguments, the same
declarations and checks); one case of each kind also runs the installed ``cbcan_node`` as a
separate process, which must print that one message and exit non-zero.
"""

from dataclasses import dataclass
import pathlib
import signal
import subprocess
import time
from typing import List, Optional, Tuple
import uuid

import pytest
from rclpy.node import Node
import yaml

from cbcan_ros.ros.config import NodeParameters
from cbcan_ros.ros.parameter_checks import ConfigurationError

from conftest import new_channel
from node_process import executable, NodeProcess, ROOT, START_TIMEOUT, STOP_TIMEOUT

CONFIGS = sorted((ROOT / 'config').glob('*.yaml'))
LONG = 'x' * 500


@dataclass(frozen=True)
class Case:
    """A bad value, and what the message must say: parameter, value as shown, allowed."""

    id: str
    arguments: Tuple[str, ...]
    says: Tuple[str, ...]
    params_file: Optional[str]  # YAML under ros__parameters, given as --params-file
    process: bool  # also run as a separate process


def case(id_, *arguments, says, params_file=None, process=False):
    """Return a case; ``arguments`` are -p overrides (name:=value) after a virtual bus."""
    overrides = [part for argument in arguments for part in ('-p', argument)]
    return Case(id_, tuple(overrides), says, params_file, process)


CASES = [
    # Type and range, as the parameter's descriptor gives them (rclpy finds these).
    case('sdo.timeout-range', 'sdo.timeout:=100.0',
         says=('parameter sdo.timeout: 100.0 is out of range', 'from 0.001 to 60.0'),
         process=True),
    case('sdo.timeout-integer-range', 'sdo.timeout:=0',
         says=('parameter sdo.timeout: 0 is out of range', 'from 0.001 to 60.0')),
    case('sdo.timeout-type', 'sdo.timeout:=abc',
         says=("parameter sdo.timeout: 'abc' is a string, not a number", 'from 0.001'),
         process=True),
    case('can.bitrate-range', 'can.bitrate:=2000000',
         says=('parameter can.bitrate: 2000000 is out of range', 'from 0 to 1000000')),
    case('can.bitrate-type', 'can.bitrate:=1.5',
         says=('parameter can.bitrate: 1.5 is a number, not an integer', 'an integer')),
    case('sdo.queue_limit-range', 'sdo.queue_limit:=0',
         says=('parameter sdo.queue_limit: 0 is out of range', 'from 1 to 10000')),
    case('sdo.read_retries-range', 'sdo.read_retries:=11',
         says=('parameter sdo.read_retries: 11 is out of range', 'from 0 to 10')),
    case('heartbeat.timeout-range', 'heartbeat.timeout:=0.0',
         says=('parameter heartbeat.timeout: 0.0 is out of range', 'from 0.01 to 3600.0')),
    case('node_guarding_period-range', 'node_guarding_period:=61.0',
         says=('parameter node_guarding_period: 61.0 is out of range', 'to 60.0')),
    case('state_publish_period-range', 'state_publish_period:=-1.0',
         says=('parameter state_publish_period: -1.0 is out of range', 'from 0.01')),
    case('read_only-type', 'read_only:=maybe',
         says=("parameter read_only: 'maybe' is a string, not true or false",
               'allowed: true or false'), process=True),
    case('sdo.block_transfer-type', 'sdo.block_transfer:=1',
         says=('parameter sdo.block_transfer: 1 is an integer, not true or false',)),
    case('simulation.eds-type', 'simulation.eds:=5',
         says=('parameter simulation.eds: 5 is an integer, not a string',)),
    # What a descriptor cannot say.
    case('can.interface-unknown', 'can.interface:=sockcan',
         says=("parameter can.interface: 'sockcan' is not a python-can interface",
               'socketcan', 'pcan', 'kvaser', 'slcan')),
    case('can.interface-long', f'can.interface:={LONG}',
         says=("parameter can.interface: 'xxxxx", "x'... is not a python-can interface"),
         process=True),
    case('can.channel-empty', "can.channel:=''",
         says=("parameter can.channel: '' is empty", 'e.g. can0')),
    case('can.channel-socketcan', 'can.interface:=socketcan', 'can.channel:=robot_arm_can_bus0',
         says=("parameter can.channel: 'robot_arm_can_bus0' is not a network interface name",
               'at most 15 characters')),
    case('can.channel-pcan', 'can.interface:=pcan', 'can.channel:=PCAN_USB1',
         says=("parameter can.channel: 'PCAN_USB1' is not a PCAN channel",
               'PCAN_USBBUS1..PCAN_USBBUS16'), process=True),
    case('can.channel-kvaser', 'can.interface:=kvaser', 'can.channel:=can0',
         says=("parameter can.channel: 'can0' is not a Kvaser channel number", '0 for')),
    case('can.channel-slcan', 'can.interface:=slcan', 'can.channel:=ttyACM0',
         says=("parameter can.channel: 'ttyACM0' is not a serial device", '/dev/ttyACM0')),
    case('can.channel-udp_multicast', 'can.interface:=udp_multicast',
         'can.channel:=10.1.2.3',
         says=("parameter can.channel: '10.1.2.3' is not a multicast address", '239.')),
    case('can.bitrate-slcan', 'can.interface:=slcan', 'can.channel:=/dev/ttyACM0',
         'can.bitrate:=800000',
         says=('parameter can.bitrate: 800000 is not a bit rate slcan sets',
               '500000', '750000'), process=True),
    case('can.bitrate-pcan', 'can.interface:=pcan', 'can.channel:=PCAN_USBBUS1',
         'can.bitrate:=300000',
         says=('parameter can.bitrate: 300000 is not a bit rate pcan sets', '250000')),
    case('can.options-not-key-value', 'can.options:=[foo]',
         says=("parameter can.options: 'foo' is not key=value", 'tty_baudrate=115200'),
         process=True),
    case('can.options-own-parameter', 'can.options:=[channel=can1]',
         says=("parameter can.options: 'channel=can1' sets channel", 'can.channel')),
    case('can.options-twice', 'can.options:=[a=1, a=2]',
         says=("parameter can.options: 'a=2' sets a a second time",)),
    case('can.options-type', 'can.options:=5',
         says=('parameter can.options: 5 is an integer, not a list of strings',
               'each key=value')),
    case('nodes-range', 'nodes:=[2, 200]',
         says=('parameter nodes: [2, 200] holds node id 200', 'node ids 1..127'), process=True),
    case('nodes-type', 'nodes:=abc',
         says=("parameter nodes: 'abc' is a string, not a list of integers", '1..127')),
    case('node_guarding-range', 'node_guarding:=[0]',
         says=('parameter node_guarding: [0] holds node id 0', 'node ids 1..127')),
    case('node_guarding-period-too-long', 'node_guarding:=[3]', 'heartbeat.timeout:=1.0',
         'node_guarding_period:=1.0',
         says=('parameter node_guarding_period: 1.0 is not shorter than heartbeat.timeout',
               'a period below 1.0'), process=True),
    case('simulation.devices-range', 'simulation.devices:=[128]',
         says=('parameter simulation.devices: [128] holds node id 128', '1..127')),
    case('simulation.drives-range', 'simulation.drives:=[0]',
         says=('parameter simulation.drives: [0] holds node id 0', '1..127')),
    case('simulation.drives-type', 'simulation.drives:=abc',
         says=("parameter simulation.drives: 'abc' is a string, not a list of integers",)),
    case('simulation.drives-overlap', 'simulation.devices:=[2, 5]', 'simulation.drives:=[5, 6]',
         says=('parameter simulation.drives: [5, 6] holds node id 5, which simulation.devices '
               '[2, 5] holds too', 'allowed: node ids that are not in simulation.devices'),
         process=True),
    case('drives.nodes-range', 'drives.nodes:=[200]',
         says=('parameter drives.nodes: [200] holds node id 200', '1..127')),
    case('drives.on_shutdown', 'drives.on_shutdown:=brake',
         says=("parameter drives.on_shutdown: 'brake' is no stop the gateway knows",
               'quick_stop, disable, none'), process=True),
    case('drives.consumer_time-off', 'drives.nodes:=[7]', 'drives.consumer_time:=0.0',
         says=('parameter drives.consumer_time: 0.0 turns off the drives stopping by '
               'themselves when the gateway dies',
               'drives.keep_running_if_gateway_dies: true'), process=True),
    case('drives.abort_connection', 'drives.abort_connection:=brake',
         says=("parameter drives.abort_connection: 'brake' is no reaction the gateway knows",
               'quick_stop, disable, fault, none')),
    case('simulation.drive_layout', 'simulation.drive_layout:=epos',
         says=("parameter simulation.drive_layout: 'epos' is no layout of a simulated drive",
               'combined, vendor, ros2_canopen, sdo_only')),
    case('drives.consumer_time-too-short', 'drives.nodes:=[7]', 'heartbeat.period:=0.1',
         'drives.consumer_time:=0.1',
         says=('parameter drives.consumer_time: 0.1 is not longer than heartbeat.period',)),
    case('drive-scale-zero', 'drives.nodes:=[7]', 'node_7.position_scale:=0.0',
         says=('parameter node_7.position_scale: 0.0 cannot convert units',
               'a number other than 0')),
    case('drive-joint-twice', 'drives.nodes:=[7, 8]', 'node_7.joint:=arm', 'node_8.joint:=arm',
         says=("parameter node_8.joint: 'arm' is the joint of node 7 as well",)),
    case('drive-heartbeat-clash', 'drives.nodes:=[7]', 'heartbeat.node_id:=7',
         says=('parameter heartbeat.node_id: 7 is also a device in drives.nodes',)),
    case('simulation.eds-missing', 'simulation.eds:=/no/such/file.eds',
         says=("parameter simulation.eds: '/no/such/file.eds' is not a readable file",)),
    case('sdo.write_allow-rule', 'sdo.write_allow:=["5:0x10000"]',
         says=("parameter sdo.write_allow: '5:0x10000' is not a valid write rule",
               'within 0x0000..0xFFFF', "'node:index'"), process=True),
    case('sdo.write_allow-long', f'sdo.write_allow:=["{LONG}"]',
         says=("parameter sdo.write_allow: 'xxxxx", "x'... is not a valid write rule")),
    case('unknown-misspelt', 'sdo.timout:=1.0',
         says=('parameter sdo.timout: 1.0 is given, but cbcan has no such parameter',
               'allowed: sdo.timeout'), process=True),
    case('unknown-close', 'node_guardng:=[3]',
         says=('parameter node_guardng: [3] is given', 'allowed: node_guarding')),
    # A node's parameter that no list of node ids made exist would do nothing, silently.
    case('drive-parameter-of-no-drive', 'nodes:=[5]', 'node_5.joint:=wheel',
         says=("parameter node_5.joint: 'wheel' is given, but node 5 is not in drives.nodes",
               'allowed: drives.nodes with 5 in it'), process=True),
    case('drive-parameter-of-no-node', 'node_6.position_scale:=1000.0',
         says=('parameter node_6.position_scale: 1000.0 is given, but node 6 is not in '
               'drives.nodes',)),
    case('eds-of-no-node', 'node_9.eds:=/robot/drive.eds',
         says=("parameter node_9.eds: '/robot/drive.eds' is given, but node 9 is in none of "
               'nodes, node_guarding, pdo.nodes or drives.nodes',)),
    case('node-parameter-without-underscore', 'drives.nodes:=[6]', 'node6.joint:=x',
         says=("parameter node6.joint: 'x' is not a parameter name: a node's parameters are "
               'node_<id>.NAME', 'allowed: node_6.joint')),
    case('node-parameter-unknown', 'nodes:=[5]', 'node_5.jiont:=x',
         says=("parameter node_5.jiont: 'x' is given, but no node has such a parameter",
               'node_<id>.joint')),
    # The same mistakes in a parameter file.
    case('file-type', says=("parameter sdo.timeout: 'fast' is a string, not a number",),
         params_file='sdo: {timeout: fast}'),
    case('file-options-as-map',
         says=('parameter can.options.tty_baudrate: 115200 is given',
               'can.options (a list of key=value strings, not a map)'),
         params_file='can: {options: {tty_baudrate: 115200}}', process=True),
    case('file-nodes-range', says=('parameter nodes: [1, 130] holds node id 130',),
         params_file='nodes: [1, 130]'),
]


def _arguments(bad: Case, folder: str) -> List[str]:
    """Return the node's arguments for a case: a private virtual bus, then the bad value."""
    arguments = ['-r', f'__ns:=/cfg{uuid.uuid4().hex[:8]}', '-p', 'can.interface:=virtual',
                 '-p', f'can.channel:=cfg-{uuid.uuid4().hex[:8]}']
    if bad.params_file:
        path = pathlib.Path(folder) / f'{bad.id}.yaml'
        path.write_text(yaml.safe_dump(
            {'/**': {'ros__parameters': yaml.safe_load(bad.params_file)}}))
        arguments += ['--params-file', str(path)]
    return arguments + list(bad.arguments)


@pytest.mark.parametrize('bad', CASES, ids=[bad.id for bad in CASES])
def test_a_bad_value_is_refused_with_a_message_naming_it(bad, tmp_path):
    node = Node('cbcan', cli_args=['--ros-args', *_arguments(bad, str(tmp_path))],
                use_global_arguments=False)
    try:
        with pytest.raises(ConfigurationError) as refused:
            NodeParameters(node).gateway_config()
    finally:
        node.destroy_node()
    for text in bad.says:
        assert text in str(refused.value), f'{text!r} missing from: {refused.value}'
    assert LONG not in str(refused.value), 'a long value came back whole'


@dataclass
class Outcome:
    """How a process with a bad value ended."""

    status: Optional[int]
    output: str


def _run_process(bad: Case, folder: str) -> Outcome:
    try:
        done = subprocess.run([executable('cbcan_node'), '--ros-args', *_arguments(bad, folder)],
                              capture_output=True, text=True, timeout=START_TIMEOUT)
    except subprocess.TimeoutExpired as expired:  # run() has killed it
        return Outcome(None, f'still running after {START_TIMEOUT} s:\n{expired.output}')
    return Outcome(done.returncode, done.stdout + done.stderr)


PROCESS_CASES = [bad for bad in CASES if bad.process]


@pytest.mark.parametrize('bad', PROCESS_CASES, ids=[bad.id for bad in PROCESS_CASES])
def test_a_bad_value_stops_the_installed_node(bad, tmp_path):
    outcome = _run_process(bad, str(tmp_path))
    assert outcome.status not in (None, 0), f'cbcan_node did not refuse it:\n{outcome.output}'
    # Only python-can's own import notes may come before it (pcan: "uptime library ...").
    messages = [line for line in outcome.output.splitlines() if 'cannot start' in line]
    assert len(messages) == 1 and 'Traceback' not in outcome.output, \
        f'not one message:\n{outcome.output}'
    assert messages[0].startswith('cbcan_node: cannot start: parameter '), messages[0]
    for text in bad.says:
        assert text in messages[0], f'{text!r} missing from: {messages[0]}'


def _config_nodes():
    """Return (file, node's full name) for each gateway each example config configures."""
    found = []
    for path in CONFIGS:
        names = [key for key in yaml.safe_load(path.read_text()) if key != '/**']
        for name in names or ['/can0/cbcan']:
            found.append(pytest.param(path, name, id=f'{path.stem}{name}'))
    return found


def _node_from_file(path: pathlib.Path, name: str, *overrides: str) -> Node:
    """Return a bare node named ``name`` that takes its parameters from ``path`` via rcl."""
    namespace, _, node_name = name.rpartition('/')
    arguments = ['--ros-args', '-r', f'__ns:={namespace}', '--params-file', str(path)]
    for override in overrides:
        arguments += ['-p', override]
    return Node(node_name, cli_args=arguments, use_global_arguments=False)


@pytest.mark.parametrize('path, name', _config_nodes())
def test_every_example_config_is_valid_as_written(path, name):
    node = _node_from_file(path, name)
    try:
        parameters = NodeParameters(node)
        config = parameters.gateway_config()  # checks everything; opens no bus
        assert parameters.warnings == [], f'{path.name} gives warnings: {parameters.warnings}'
        if path.stem == 'two_buses':  # each bus its section, on top of the shared one
            bus = name.split('/')[1]
            assert config.channel == bus
            assert config.heartbeat_timeout == {'can0': 0.5, 'can1': 1.0}[bus]
            assert config.interface == 'socketcan'
    finally:
        node.destroy_node()


def test_an_integer_for_a_number_is_taken_as_that_number():
    node = _node_from_file(ROOT / 'config' / 'simulation.yaml', '/can0/cbcan', 'sdo.timeout:=2')
    try:
        assert NodeParameters(node).gateway_config().sdo_timeout == 2.0
    finally:
        node.destroy_node()


def test_the_example_configs_start_the_installed_node():
    """Each example as a user starts it; only the interface is python-can's ``virtual``."""
    started = []
    try:
        for param in _config_nodes():
            path, name = param.values
            namespace = name.rpartition('/')[0]
            started.append((param.id, NodeProcess(
                ['-r', f'__ns:={namespace}', '--params-file', str(path),
                 '-p', 'can.interface:=virtual'])))
        for id_, process in started:
            deadline = time.monotonic() + START_TIMEOUT
            while 'CANopen gateway on virtual' not in process.output():
                assert process.process.poll() is None and time.monotonic() < deadline, \
                    f'{id_} did not start:\n{process.output()}'
                time.sleep(0.05)
        for _, process in started:  # all at once: each takes a moment to shut down
            process.process.send_signal(signal.SIGINT)
        for id_, process in started:
            assert process.wait(STOP_TIMEOUT) == 0, f'{id_}:\n{process.output()}'
            assert 'WARN' not in process.output(), f'{id_}:\n{process.output()}'
    finally:
        for _, process in started:
            process.close()


# Arguments rcl or python-can refuse before the parameter checks see them: "stop the node at
# start with a message naming the parameter, exit status 1, no traceback".

@pytest.mark.parametrize('bad', [['-p', "nodes:=[1, 'a']"],
                                 ['--params-file', '/nonexistent/cbcan.yaml']])
def test_malformed_parameter_override_stops_the_node_without_a_traceback(start_node, bad):
    # Once a defect: rclpy.init parsed --ros-args outside main()'s guard, and its RCLError
    # escaped as a traceback.
    gateway = start_node(['-p', f'can.channel:={new_channel()}', *bad])
    status = gateway.wait(START_TIMEOUT)
    output = gateway.output()
    assert status == 1, output
    assert 'Traceback' not in output, output


def test_unknown_can_interface_stops_the_node_at_start(start_node):
    # Once a defect: python-can said at once that the interface does not exist, and the node
    # kept "reopening until it works" for ever instead of naming can.interface.
    gateway = start_node(['-p', 'can.interface:=no_such_interface',
                          '-p', f'can.channel:={new_channel()}'])
    status = gateway.wait(START_TIMEOUT)
    output = gateway.output()
    assert status == 1, output
    assert 'can.interface' in output and 'Traceback' not in output, output


def test_a_canopen_release_other_than_the_supported_one_stops_the_gateway_naming_both(
        monkeypatch):
    import canopen

    from cbcan_ros.core.canopen_gaps import version_problem
    from cbcan_ros.core.gateway import Gateway, GatewayConfig
    assert version_problem() == ''  # the one installed here (requirements.txt pins it)
    monkeypatch.setattr(canopen, '__version__', '2.5.0')
    with pytest.raises(RuntimeError) as refused:
        Gateway(GatewayConfig())
    assert 'canopen 2.5.0 is installed' in str(refused.value)
    assert 'canopen 2.4.x only' in str(refused.value)
    assert "pip install 'canopen==2.4.1'" in str(refused.value)


def test_a_device_file_of_the_bus_description_that_is_not_there_is_named_by_its_key(tmp_path):
    # The dcf becomes the parameter node_10.eds inside the gateway: a message naming that
    # parameter sends the user looking for something they never set.
    bus = tmp_path / 'bus.yml'
    bus.write_text('nodes:\n  io:\n    node_id: 10\n    dcf: /nonexistent/x.eds\n')
    outcome = _run_process(case('bus-dcf', f'bus_config:={bus}', says=()), str(tmp_path))
    assert outcome.status not in (None, 0), outcome.output
    assert (f"cannot start: nodes.io.dcf of the bus description {bus}: '/nonexistent/x.eds': "
            f'no such file') in outcome.output, outcome.output
