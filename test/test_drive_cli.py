"""cbcan_cli drive, move, target and drives, run as a user runs them, against a simulated drive.

Each test starts a gateway in this process (conftest's Harness, named ``/cbcan``) with one
durand CiA 402 drive on a virtual bus of its own. The CLI reaches it over DDS as it reaches
any gateway: most commands through one cbcan_cli client in this process (a new client finds
the gateway in 1-2 s), the Ctrl-C of a move and a target nobody subscribes as the installed
executable in a process of its own. What a command did is read from the drive itself;
conditions are waited for with generous ceilings, never proved by sleeping.
"""

import signal
import subprocess
import threading
from typing import List

import pytest

from cbcan_ros.msg import DriveState
from cbcan_ros.ros.cli import build_parser, Client, run
from cbcan_ros.ros.drives import STATE_QOS
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos

from conftest import Harness, new_channel, wait_until
from node_process import executable

NODE = 7
NOT_A_DRIVE = 9
JOINT = 'shoulder'
GATEWAY = '/cbcan'  # the Harness's node
SCALE = 1000.0  # counts per rad, counts/s per rad/s
WAIT = 15.0

PDOS = default_drive_pdos()  # the simulated drive's own, as make run has them


class Axis:
    """A gateway with drive NODE, and ``cli(*arguments) -> (status, out, err)`` to work it."""

    def __init__(self, start_durand, capsys):
        channel = new_channel()
        self.drive = start_durand(NODE, kind=DurandDrive, channel=channel, pdos=PDOS)
        wait_until(lambda: self.drive.running, WAIT, 'the drive receiving')
        self.gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                                'drives.nodes': [NODE], f'node_{NODE}.joint': JOINT,
                                f'node_{NODE}.position_scale': SCALE,
                                f'node_{NODE}.velocity_scale': SCALE,
                                'drives.command_timeout': 0.0, 'drives.consumer_time': 3.0})
        self._capsys = capsys
        self._lock = threading.Lock()
        self._states: List[DriveState] = []
        self.gateway.client_node.create_subscription(
            DriveState, f'{GATEWAY}/node_{NODE}/drive_state', self._keep, STATE_QOS)
        assert self.gateway.call('nmt_command', node_id=NODE, command=1).success
        wait_until(lambda: self.latest_state() not in (None, 'UNKNOWN'), WAIT,
                   'the drive state published')
        self.client = Client(GATEWAY, WAIT)

    def _keep(self, message: DriveState) -> None:
        with self._lock:
            self._states.append(message)

    def latest_state(self):
        """Return the state of the gateway's latest drive_state message, None before one."""
        with self._lock:
            return self._states[-1].state if self._states else None

    def cli(self, *arguments: str):
        """Run one cbcan_cli command through the test's client; return (status, out, err)."""
        status = run(self.client, build_parser().parse_args(arguments))
        out, err = self._capsys.readouterr()
        return status, out, err

    def close(self) -> None:
        """Close the client, then the gateway."""
        self.client.close()
        self.gateway.close()


@pytest.fixture
def axis(ros_context, start_durand, capsys):
    """Return a gateway with one simulated drive and the CLI's client of it."""
    made = Axis(start_durand, capsys)
    yield made
    made.close()


def cli_process(*arguments: str) -> subprocess.Popen:
    """Start the installed cbcan_cli with ``arguments``, its output in one pipe."""
    return subprocess.Popen([executable('cbcan_cli'), '--gateway', GATEWAY, *arguments],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_enable_by_mode_name_prints_the_state_mode_and_statusword(axis):
    status, out, err = axis.cli('drive', str(NODE), 'enable', '--mode', 'CSV')
    assert status == 0, err
    assert out.startswith(f'ok: node {NODE} enable: OPERATION_ENABLED, cyclic synchronous '
                          f'velocity (CSV), statusword 0x'), out
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    status, out, err = axis.cli('drive', str(NODE), 'disable')
    assert status == 0, err
    assert out.startswith(f'ok: node {NODE} disable: SWITCH_ON_DISABLED'), out
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'


def test_an_nmt_stop_refused_for_an_enabled_drive_is_not_called_an_sdo_abort(axis):
    # A new user's walkthrough: "error: SDO abort 0x08000022: drive 6 is OPERATION_ENABLED".
    status, _, err = axis.cli('drive', str(NODE), 'enable', '--mode', 'CSV')
    assert status == 0, err
    status, out, err = axis.cli('nmt', str(NODE), 'stop')
    assert status == 1, out + err
    assert err.startswith(f'error: NMT command stop to node {NODE}: 0x08000022'), err
    assert 'SDO abort' not in err, err
    assert axis.drive.drive_state == 'OPERATION_ENABLED'


@pytest.mark.parametrize('mode', ['xyz', '2', 'cs'])
def test_a_bad_mode_is_refused_naming_the_modes_and_nothing_is_enabled(axis, capsys, mode):
    with pytest.raises(SystemExit) as exited:
        build_parser().parse_args(['drive', str(NODE), 'enable', '--mode', mode])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert f"'{mode}' is not a CiA 402 mode" in err and 'csv (9)' in err, err
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'


def test_set_mode_without_a_mode_is_refused_before_anything_is_sent(axis):
    status, out, err = axis.cli('drive', str(NODE), 'set-mode')
    assert (status, out) == (2, '')
    assert 'set-mode needs --mode MODE' in err


def test_move_reaches_the_position_printing_feedback(axis):
    assert axis.cli('drive', str(NODE), 'enable', '--mode', 'pp')[0] == 0
    status, out, err = axis.cli('move', str(NODE), '2.0', '--velocity', '20')
    assert status == 0, err
    lines = out.splitlines()
    assert lines[-1] == f'ok: node {NODE} reached position 2', out
    assert lines[0].startswith(f'node {NODE}: position '), out
    assert axis.drive.position == 2000
    status, out, err = axis.cli('move', str(NODE), '0.5', '--relative', '--velocity', '20')
    assert status == 0, err
    assert out.splitlines()[-1] == f'ok: node {NODE} reached position 2.5', out
    assert axis.drive.position == 2500


def test_a_target_in_csv_sets_the_drive_velocity(axis):
    assert axis.cli('drive', str(NODE), 'enable', '--mode', 'csv')[0] == 0
    status, out, err = axis.cli('target', str(NODE), '1.5')
    assert status == 0, err
    assert out == (f'ok: node {NODE} target 1.5 sent (a velocity in cyclic synchronous '
                   f'velocity (CSV))\n')
    wait_until(lambda: axis.drive.velocity == 1500, WAIT, 'the drive at 1500 counts/s')


def test_a_target_for_a_drive_not_enabled_is_refused_with_the_way_to_enable(axis):
    status, out, err = axis.cli('target', str(NODE), '1.5')
    assert (status, out) == (1, '')
    assert f'node {NODE} is SWITCH_ON_DISABLED' in err and 'enable --mode' in err, err
    assert axis.drive.velocity == 0


def test_drives_lists_each_drive_with_state_mode_position_and_error(axis):
    assert axis.cli('drive', str(NODE), 'enable', '--mode', 'pp')[0] == 0
    assert axis.cli('move', str(NODE), '0.25', '--velocity', '20')[0] == 0
    axis.drive.inject_fault(0x2310)
    wait_until(lambda: axis.latest_state() == 'FAULT', WAIT, 'drive_state FAULT')
    status, out, err = axis.cli('drives')
    assert status == 0, err
    header, line = out.splitlines()
    assert header.split() == ['node', 'joint', 'state', 'mode', 'position', 'velocity',
                              'error']
    assert line.split() == [str(NODE), JOINT, 'FAULT', 'PP', '0.25', '0', '0x2310',
                            'continuous', 'over-current'], out


def test_drives_without_a_gateway_exits_2():
    finished = subprocess.run([executable('cbcan_cli'), '--gateway', '/no/such/gateway',
                               '--wait', '1', 'drives'], capture_output=True, text=True,
                              timeout=60.0)
    assert finished.returncode == 2, finished.stderr
    assert 'no gateway at /no/such/gateway' in finished.stderr


@pytest.mark.parametrize('arguments', [
    ['drive', str(NOT_A_DRIVE), 'enable', '--mode', 'csv'],
    ['move', str(NOT_A_DRIVE), '1.0'],
])
def test_a_command_to_a_node_that_is_not_a_drive_shows_the_gateways_refusal(axis, arguments):
    status, out, err = axis.cli(*arguments)
    assert (status, out) == (1, '')
    assert f'node {NOT_A_DRIVE} is not a drive (parameter drives.nodes: [{NODE}])' in err, err
    assert 'nothing was sent' in err


def test_a_target_for_a_node_that_is_not_a_drive_names_the_drives(axis):
    assert axis.cli('drives')[0] == 0  # the client knows the gateway's topics from here on
    axis.client.wait = 2.0  # what is left to wait for is a match that never comes
    status, out, err = axis.cli('target', str(NOT_A_DRIVE), '1.0')
    assert (status, out) == (2, '')
    assert (f'node {NOT_A_DRIVE} is not a drive of {GATEWAY}: nothing subscribes '
            f'node_{NOT_A_DRIVE}/target (its drives: [{NODE}]' in err), err


def test_drives_of_a_gateway_without_drives_exits_1(make_gateway, capsys):
    make_gateway()
    with Client(GATEWAY, WAIT) as client:
        client.node_states()  # the gateway is found: its topics are known from here on
        client.wait = 2.0
        status = run(client, build_parser().parse_args(['drives']))
    out, err = capsys.readouterr()
    assert (status, out) == (1, '')
    assert f'{GATEWAY} has no drives (its parameter drives.nodes is empty)' in err, err


def test_ctrl_c_cancels_a_move_and_prints_where_the_drive_halted(axis):
    assert axis.cli('drive', str(NODE), 'enable', '--mode', 'pp')[0] == 0
    process = cli_process('--wait', str(WAIT), 'move', str(NODE), '100', '--velocity', '1')
    printed: List[str] = []
    reader = threading.Thread(target=lambda: printed.extend(process.stdout), daemon=True)
    reader.start()
    try:
        # Interrupted once under way: feedback can come before the drive's first step.
        under_way = f'node {NODE}: position '
        wait_until(lambda: any(line.startswith(under_way) and
                               float(line[len(under_way):].split(',')[0]) > 0
                               for line in printed),
                   WAIT * 2, f'feedback of the move under way; printed: {printed}')
        process.send_signal(signal.SIGINT)
        assert process.wait(WAIT * 2) == 130, ''.join(printed)
    finally:
        process.kill()
        reader.join(WAIT)
    halted = [line for line in printed if line.startswith('cancelled: ')]
    assert len(halted) == 1, ''.join(printed)
    position = float(halted[0].split('halted at position ')[1].split()[0])
    assert 0 < position < 100
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the drive standing')
    assert axis.drive.position == round(position * SCALE)
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
