"""Every code block of README.md and docs/ that can run here runs as printed; the others say why.

Each fenced block of every page is one of:
- ``python``: run as a script in its own process against the gateway ``make run`` starts;
  every ``# -> TEXT`` comment is a line the script must print, in that order (``# e.g.``
  comments show output that varies);
- ``bash`` whose every command is ``make run``, ``make cli ARGS="..."`` or ``cbcan_cli ...``:
  run against that gateway (``make cli`` as the ``cbcan_cli`` it runs); a block written as a
  terminal session (``$ cbcan_cli ...`` and the lines it prints) must print exactly those
  lines;
- ``yaml``: gateway parameters are checked as the gateway checks its parameters at start
  (it refuses a name it does not declare), and the one naming node 5's EDS is given to that
  gateway; the diagnostic_aggregator configuration must name the status items the gateway
  publishes; a bus description (``master:``, ``nodes:``) is read and its boots worked out as
  at start, with the shipped EDS files under the names it gives, and uses no key the gateway
  leaves out;
- listed in ``NOT_RUN`` with the reason it cannot run here.
A block that is none of these fails the test, so a new block is run or listed. Every Python
block, run or not, is complete as printed: ruff finds no undefined name in it. Every
``cbcan_cli`` command of a shell block, run or not, is a command line ``cbcan_cli`` takes (or
the page shows argparse's answer to it). Every relative link of the pages leads to a file that
exists (and to a heading of it, when it names one), and the README links every page of docs/.
"""

from dataclasses import dataclass
import pathlib
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
from typing import Dict, List, Tuple

from diagnostic_msgs.msg import DiagnosticArray
import pytest
from rclpy.node import Node
import yaml

from cbcan_ros.core import eds
from cbcan_ros.core.boot.description import load as load_bus_description
from cbcan_ros.core.boot.plan import boot_settings
from cbcan_ros.ros.cli import build_parser, Client, DEFAULT_GATEWAY, run
from cbcan_ros.ros.client import GatewayError
from cbcan_ros.ros.config import NodeParameters
from cbcan_ros.ros.diagnostics import DIAGNOSTICS_QOS

from conftest import wait_until
from node_process import EDS, NodeProcess, ROOT, START_TIMEOUT

# One worker runs the module, so its gateway starts once.
pytestmark = pytest.mark.xdist_group('documentation')

README = ROOT / 'README.md'
DOCS = ROOT / 'docs'
# Every page whose code blocks are run or listed: the front page and every page of docs/.
PAGES = [README, *sorted(DOCS.glob('*.md'))]
# What the aggregator example names the gateway's status items after.
AGGREGATOR_GATEWAY = '/can0/cbcan'
# The EDS path the parameter example of the command line page gives; the test puts a copy of
# config/simulated_device.eds at a path of its own and reads the page with that path.
DOCUMENTED_EDS = '/home/robot/eds/drive_5.eds'
# The folder and files a bus description example names; the test puts the shipped EDS files
# there under those names.
DOCUMENTED_DCF_PATH = '/robot/eds'
DOCUMENTED_DCFS = {'io_module.eds': ROOT / 'config' / 'simulated_device.eds',
                   'cia402_drive.eds': ROOT / 'config' / 'cia402_drive.eds'}
SCRIPT_TIMEOUT = 120.0

# A piece of the block that names it: why it does not run here.
NOT_RUN = {
    'drives/              service.py (DriveService)': 'a picture of the package tree, not code',
    'git clone <this repository>': 'a ROS 2 workspace: rosdep, colcon on a ROS install and '
                                   'the ros2 CLI are not on this machine (make colcon-smoke '
                                   'builds and runs the package as such a workspace does)',
    'sudo apt install python3-can': 'installs system packages',
    'ip -details link show can0': 'SocketCAN: this kernel has none, and it needs root',
    'config/pcan.yaml': 'the ros2 CLI and a PEAK adapter',
    'can.interface:=kvaser': 'the ros2 CLI and a Kvaser adapter',
    'config/slcan.yaml': 'the ros2 CLI and an slcan adapter (test_config starts this file '
                         'against a fake adapter)',
    'sudo slcand': 'slcand, a kernel module and root',
    'buses:=can0,can1': 'SocketCAN, root and ros2 launch (test_launch runs the launch file)',
    'cbcan_node: cannot start:': 'the output of a node given wrong values: test_config checks '
                                 'these messages',
    'ros2 lifecycle set': 'the ros2 CLI (test_lifecycle drives the same transitions)',
    'SdoRead request:': 'a summary of srv_defs/srv/SdoRead.srv and SdoWrite.srv, not code',
    'SdoBatch request:': 'a summary of srv_defs/srv/SdoBatch.srv, not code',
    'NmtCommand request:': 'a summary of srv_defs/srv/NmtCommand.srv and NmtState.srv',
    'ros2 service call /can0/cbcan/sdo_write': 'the ros2 CLI',
    'ros2 service call /can0/cbcan/nmt_command': 'the ros2 CLI',
    'ros2 topic echo /can0/cbcan/emcy': 'the ros2 CLI',
    'cbcan_cli lss-scan --assign-from 10 --store': 'unconfigured LSS devices, which the '
                                                   'simulation of make run has not: '
                                                   'test_lss_process runs these steps',
    'cbcan_cli lss-inquire 0x319': 'a device with LSS at that identity: test_lss_process runs '
                                   'these steps',
    'node_6: {eds: /robot/eds/drive.eds}': 'a CiA 402 drive and its EDS (test_pdo_topics runs '
                                           'the same PDO and SYNC flow against durand)',
    'def on_drive(message):': 'runs until Ctrl-C: test_pdo_worked_example_runs_as_printed_'
                              'against_the_simulated_drive runs it as printed and stops it',
    'cbcan_cli pdo-write 6 1 Controlword=6': 'names from the EDS of a real drive, which make '
                                             "run's node 6 has not (test_pdo_cli runs "
                                             'pdo-echo and pdo-write against durand)',
    'cbcan_cli drive 7 enable --mode pp': 'the positions a move prints on the way vary from '
                                          'run to run: test_drive_cli runs these commands '
                                          'against a simulated drive',
    'LssScan request:': 'a summary of srv_defs/srv/LssScan.srv, LssConfigure.srv and '
                        'LssInquire.srv',
    'joint_state_topic_hardware_interface/JointStateTopicSystem': 'a ros2_control robot '
                                                                  'description: ros2_control '
                                                                  'is not on this machine',
    'cbcan_cli dump 700:780 --count 3': "raw.filters and raw.send_allow, which make run's "
                                        'gateway has not (simulation.yaml needs no can_msgs): '
                                        'test_raw_cli runs dump and send',
    '0x705 [1] 7F  heartbeat node 5': 'output of cbcan_cli dump: test_raw_cli checks lines',
    'ros2 run my_bms bms_node': 'the ros2 CLI and a program written for ros2_socketcan',
    'cbcan_cli program-download 8 /home/robot/firmware': "a real device's firmware file, and "
                                                         'its speed varies: the Python block '
                                                         "beside it downloads into make run's "
                                                         'node 8, test_program_download runs '
                                                         'the command',
    'software_file: firmware/io_v2.bin': 'names a firmware file that is not on this machine: '
                                         'test_program_download boots such a description '
                                         'against a simulated bootloader',
}
# Commands of a cbcan_cli block that are not cbcan_cli calls: why they do not run here.
NOT_RUN_COMMANDS = {
    'make run': 'the gateway every block here runs against is started as this recipe starts it',
    'make test': 'the test suite, of which this test is a part',
}


@dataclass
class Block:
    """One fenced code block of a page."""

    page: str
    line: int
    language: str
    text: str

    def __str__(self) -> str:
        first = self.text.strip().splitlines()[0] if self.text.strip() else ''
        return f'{self.page} line {self.line} ({self.language or "no language"}): {first[:70]}'

    @property
    def name(self) -> str:
        """Return a short name of the block for test ids and file names."""
        return f'{pathlib.Path(self.page).stem}-line{self.line}'


def page_blocks(page: pathlib.Path) -> List[Block]:
    """Return every fenced code block of one page, indented ones too."""
    text = page.read_text(encoding='utf-8')
    blocks = []
    for match in re.finditer(r'^( *)```(\w*)\n(.*?)^\1```$', text, re.S | re.M):
        indent = len(match.group(1))
        body = '\n'.join(line[indent:] for line in match.group(3).splitlines())
        blocks.append(Block(str(page.relative_to(ROOT)), text.count('\n', 0, match.start()) + 1,
                            match.group(2), body))
    return blocks


def all_blocks() -> List[Block]:
    """Return every fenced code block of every page, page by page."""
    return [block for page in PAGES for block in page_blocks(page)]


def session(block: Block) -> List[Tuple[str, List[str]]]:
    """Return the commands of a shell block, each with the lines it is shown to print.

    Continuation lines are joined and comment lines dropped. In a terminal session (lines
    starting ``$ ``) the lines after a command are its output; elsewhere none is shown.
    """
    lines = block.text.replace('\\\n', ' ').splitlines()
    if not any(line.startswith('$ ') for line in lines):
        return [(line.strip(), []) for line in lines if shlex.split(line, comments=True)]
    steps = []
    for line in lines:
        if line.startswith('$ '):
            steps.append((line[2:].strip(), []))
        elif steps:
            steps[-1][1].append(line)
    return steps


def cli_arguments(command: str):
    """Return the cbcan_cli arguments of a command, None when it is not a cbcan_cli call."""
    words = shlex.split(command, comments=True)
    if words[:1] == ['cbcan_cli']:
        return words[1:]
    if words[:2] == ['make', 'cli'] and len(words) == 3 and words[2].startswith('ARGS='):
        return shlex.split(words[2][len('ARGS='):])
    return None


def kind(block: Block) -> str:
    """Return how the test takes a block: python, cli, parameters, aggregator or not-run."""
    listed = [piece for piece in NOT_RUN if piece in block.text]
    if listed:
        return 'not-run'
    if block.language == 'python':
        return 'python'
    if block.language == 'yaml':
        keys = list(yaml.safe_load(block.text))
        if keys == ['analyzers']:
            return 'aggregator'
        if 'master' in keys or 'nodes' in keys:
            return 'bus'
        if all(key.startswith('/') for key in keys):
            return 'parameters'
    if block.language == 'bash' and all(
            cli_arguments(command) is not None
            or ' '.join(shlex.split(command, comments=True)) in NOT_RUN_COMMANDS
            for command, _output in session(block)):
        return 'cli'
    return 'unclassified'


def blocks_of(wanted: str) -> List[Block]:
    return [block for block in all_blocks() if kind(block) == wanted]


def test_every_block_is_run_or_listed_with_a_reason():
    blocks = all_blocks()
    assert len(blocks) > 30, 'the pages have fewer code blocks than expected: parsing broke'
    kinds = [kind(block) for block in blocks]
    unclassified = [str(block) for block, taken in zip(blocks, kinds, strict=True)
                    if taken == 'unclassified']
    assert not unclassified, ('neither run by this test nor listed in NOT_RUN with a reason '
                              f'(run them here or list them): {unclassified}')
    for piece in NOT_RUN:
        named = [str(block) for block in blocks if piece in block.text]
        assert len(named) == 1, f'NOT_RUN entry {piece!r} names {len(named)} blocks: {named}'
    assert {'python', 'cli', 'parameters', 'aggregator'} <= set(kinds), kinds


def test_every_page_has_code_blocks_and_the_readme_links_every_page():
    linked = {target for _text, target in links(README)}
    unlinked = [page.name for page in DOCS.glob('*.md') if f'docs/{page.name}' not in linked]
    assert not unlinked, f'README.md links no {unlinked}'
    assert [page for page in PAGES if page_blocks(page)], 'no page has a code block'


def anchor(heading: str) -> str:
    """Return the anchor GitHub gives a heading: lower case, punctuation dropped, - for spaces."""
    return re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')


def anchors(page: pathlib.Path) -> List[str]:
    """Return the anchors of every heading of a page, code blocks left out."""
    text = re.sub(r'^( *)```.*?^\1```$', '', page.read_text(encoding='utf-8'), flags=re.S | re.M)
    return [anchor(heading) for heading in re.findall(r'^#+ (.*)$', text, re.M)]


def links(page: pathlib.Path) -> List[Tuple[str, str]]:
    """Return every link of a page outside code blocks: (its text, its target)."""
    text = re.sub(r'^( *)```.*?^\1```$', '', page.read_text(encoding='utf-8'), flags=re.S | re.M)
    return re.findall(r'\[([^\]]*)\]\(([^)\s]+)\)', text)


@pytest.mark.parametrize('page', PAGES, ids=lambda page: page.name)
def test_relative_links_lead_to_a_file_and_heading(page):
    broken = []
    for text, target in links(page):
        if re.match(r'[a-z]+:', target):
            continue  # a web address
        path, _, fragment = target.partition('#')
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f'[{text}]({target}): no file {file}')
        elif fragment and (file.suffix != '.md' or fragment not in anchors(file)):
            broken.append(f'[{text}]({target}): no heading #{fragment} in {file.name}')
    assert not broken, f'{page.name}: {broken}'


@pytest.mark.parametrize('block', [block for block in all_blocks()
                                   if block.language == 'python'], ids=lambda block: block.name)
def test_python_blocks_are_complete_as_printed(block):
    """Run or not, a Python block imports or defines every name it uses, and nothing unused."""
    ruff = shutil.which('ruff')
    assert ruff, 'ruff is not installed (make venv installs it)'
    checked = subprocess.run([ruff, 'check', '--no-cache', '--isolated', '--select', 'F',
                              '--stdin-filename', 'example.py', '-'], input=block.text,
                             capture_output=True, text=True)
    assert checked.returncode == 0, f'{block}\n{checked.stdout}{checked.stderr}'


@pytest.mark.parametrize('block', [block for block in all_blocks()
                                   if block.language == 'bash'], ids=lambda block: block.name)
def test_cli_commands_are_valid_command_lines_as_printed(block, capsys):
    """Run or not, every cbcan_cli command of a shell block is one cbcan_cli takes."""
    for command, shown in session(block):
        arguments = cli_arguments(command)
        if arguments is None:
            continue
        try:
            build_parser().parse_args(arguments)
        except SystemExit:
            # A wrong command line the page shows as such, with argparse's own answer.
            usage = capsys.readouterr().err.splitlines()
            assert usage and usage == shown, f'{block}: {command}\n{usage}'


def make_run_arguments() -> List[str]:
    """Return the arguments the Makefile's ``run`` recipe starts cbcan_node with."""
    recipe = re.search(r'^run:.*\n\t.*cbcan_node (.*)$', (ROOT / 'Makefile').read_text(), re.M)
    assert recipe, 'the Makefile has no run recipe starting cbcan_node'
    words = shlex.split(recipe.group(1).replace('$(ROOT)', str(ROOT)))
    assert words[0] == '--ros-args' and words[-1] == '$(ARGS)', words
    return words[1:-1]


def parameter_file(block: Block, folder: pathlib.Path) -> pathlib.Path:
    """Write a parameter block to a file, with a copy of the simulated EDS as node 5's EDS."""
    eds = folder / 'drive_5.eds'
    eds.write_text(pathlib.Path(EDS).read_text())
    path = folder / f'parameters_{block.name}.yaml'
    path.write_text(block.text.replace(DOCUMENTED_EDS, str(eds)))
    return path


@pytest.mark.parametrize('block', blocks_of('bus'), ids=lambda block: block.name)
def test_bus_description_examples_are_taken_by_the_gateway(block, tmp_path):
    for name, source in DOCUMENTED_DCFS.items():
        shutil.copy(source, tmp_path / name)
    path = tmp_path / 'bus.yml'
    path.write_text(block.text.replace(f'dcf_path: {DOCUMENTED_DCF_PATH}',
                                       f'dcf_path: {tmp_path}'))
    description = load_bus_description(str(path))
    assert description.unsupported == (), f'{block}: {description.unsupported}'
    dictionaries = {device.node_id: eds.load(device.dcf, device.node_id)
                    for device in description.devices}
    drives = [device.node_id for device in description.devices if device.driver == 'drive']
    settings = boot_settings(description, (), dictionaries, description.master.node_id,
                             lambda node_id: 300, drives, list(dictionaries))
    assert [plan.node_id for plan in settings.plans] == sorted(dictionaries)


@pytest.mark.parametrize('block', blocks_of('parameters'), ids=lambda block: block.name)
def test_parameter_examples_are_taken_by_the_gateway(block, tmp_path):
    node = Node('cbcan', cli_args=['--ros-args', '-r', '__ns:=/can0', '--params-file',
                                   str(parameter_file(block, tmp_path))],
                use_global_arguments=False)
    try:
        parameters = NodeParameters(node)  # refuses a name the gateway does not declare
        parameters.gateway_config()  # checks every value; opens no bus
        assert parameters.warnings == [], f'{block}: {parameters.warnings}'
    finally:
        node.destroy_node()


@pytest.fixture(scope='module')
def gateway(tmp_path_factory):
    """Start the gateway as ``make run`` does, with the documented parameter file on top.

    That file names node 5's EDS by a path of this machine: a copy of the simulated device's.
    Yields the process and the path of the EDS copy.
    """
    folder = tmp_path_factory.mktemp('documentation')
    named = [block for block in blocks_of('parameters') if DOCUMENTED_EDS in block.text]
    assert len(named) == 1, [str(block) for block in named]
    parameters = parameter_file(named[0], folder)
    process = NodeProcess([*make_run_arguments(), '--params-file', str(parameters)])
    try:
        yield process, str(folder / 'drive_5.eds')
    finally:
        process.close()


@pytest.fixture(scope='module')
def cli_client(gateway):
    """Yield one cbcan_cli client of the gateway, once it answers.

    The examples then wait only for their own discovery (1-2 s), not for the gateway's start.
    """
    client = Client(DEFAULT_GATEWAY, START_TIMEOUT)
    try:
        client.state(5)
    except GatewayError as error:
        client.close()
        raise AssertionError(f'{error}\ncbcan_node output:\n{gateway[0].output()}') from None
    yield client
    client.close()


def expected_lines(script: str) -> List[str]:
    return [line.split('# -> ', 1)[1].strip() for line in script.splitlines()
            if '# -> ' in line]


@pytest.mark.parametrize('block', blocks_of('python'), ids=lambda block: block.name)
def test_python_examples_run_as_printed(gateway, cli_client, block, tmp_path):
    script = tmp_path / 'example.py'
    script.write_text(block.text)
    finished = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                              timeout=SCRIPT_TIMEOUT, cwd=tmp_path)
    report = (f'{block}\nstdout:\n{finished.stdout}\nstderr:\n{finished.stderr}\n'
              f'cbcan_node output:\n{gateway[0].output()}')
    assert finished.returncode == 0, report
    printed = iter(finished.stdout.splitlines())
    for expected in expected_lines(block.text):
        assert any(line == expected for line in printed), f'{expected!r} not printed\n{report}'


def test_cli_examples_run_as_printed(gateway, cli_client, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)  # the examples name files of the repository by relative paths
    ran = 0
    for block in blocks_of('cli'):
        for command, shown in session(block):
            arguments = cli_arguments(command)
            if arguments is None:
                continue  # one of NOT_RUN_COMMANDS
            args = build_parser().parse_args(arguments)
            assert args.gateway == DEFAULT_GATEWAY, f'{block}: {command}'
            status = run(cli_client, args)
            out, err = capsys.readouterr()
            said = (f'{block}\n$ {command}\nstatus {status}\nstdout:\n{out}stderr:\n{err}'
                    f'cbcan_node output:\n{gateway[0].output()}')
            if shown:
                expected = [line.replace(DOCUMENTED_EDS, gateway[1]) for line in shown]
                assert (out + err).splitlines() == expected, said
            else:
                assert status == 0, said
            ran += 1
    assert ran >= 10, f'only {ran} cbcan_cli commands found in the pages'


def test_diagnostic_aggregator_example_names_what_the_gateway_publishes(gateway, cli_client,
                                                                      client_node):
    blocks = blocks_of('aggregator')
    assert len(blocks) == 1, [str(block) for block in blocks]
    groups = yaml.safe_load(blocks[0].text)['analyzers']['ros__parameters']['can']['analyzers']
    names: Dict[str, int] = {}
    lock = threading.Lock()

    def on_diagnostics(message: DiagnosticArray) -> None:
        with lock:
            for status in message.status:
                names[status.name] = status.level

    client_node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics,
                                    DIAGNOSTICS_QOS)
    expected = groups['can0']['expected']
    assert groups['can0']['find_and_remove_prefix'] == [f'{AGGREGATOR_GATEWAY}: ']

    def published():
        with lock:
            return all(name in names for name in expected)
    wait_until(published, START_TIMEOUT, f'{expected} on /diagnostics (seen {names}); '
                                         f'cbcan_node output:\n{gateway[0].output()}')


def test_pdo_worked_example_runs_as_printed_against_the_simulated_drive(gateway, cli_client,
                                                                        tmp_path):
    """The example receives TPDOs 1 and 2 of node 6, sends RPDO 1, and stops on Ctrl-C."""
    blocks = [block for block in all_blocks() if 'def on_drive(message):' in block.text]
    assert len(blocks) == 1, [str(block) for block in blocks]
    assert run(cli_client, build_parser().parse_args(['nmt', '6', 'start'])) == 0
    script = tmp_path / 'pdo_example.py'
    script.write_text(blocks[0].text)
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    printed: List[str] = []
    reader = threading.Thread(target=lambda: printed.extend(process.stdout), daemon=True)
    reader.start()
    try:
        # The controlword it sent (shutdown) shows in the statusword: ready to switch on.
        wait_until(lambda: any('statusword 0x0231, position' in line for line in printed),
                   SCRIPT_TIMEOUT, f'{blocks[0]} to print the state it sent the drive to; '
                                   f'printed: {printed}')
        process.send_signal(signal.SIGINT)
        assert process.wait(SCRIPT_TIMEOUT) == 0, ''.join(printed)
    finally:
        process.kill()
        reader.join(SCRIPT_TIMEOUT)
