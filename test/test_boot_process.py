"""Boot configuration through the installed ``cbcan_node`` and ``cbcan_cli``, each a process.

Two durand devices run in this test process on the node's udp_multicast bus; the node boots
them from a bus description. A robot program sees the boots on ``~/boot_states`` (a late
subscriber too) and ``/diagnostics``, and runs one again with ``cbcan_cli boot``.
"""

import pathlib
import struct
import subprocess
import textwrap
import uuid

from diagnostic_msgs.msg import DiagnosticArray

from cbcan_ros.msg import BootStates
from cbcan_ros.ros.boot import BOOT_STATES_QOS
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import wait_until
from node_process import executable, private_bus, START_TIMEOUT

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = ROOT / 'config' / 'simulated_device.eds'
WAIT = 20.0

BUS = """\
    master:
      node_id: 1
      heartbeat_producer: 100
    nodes:
      conveyor:
        node_id: 10
        dcf: {eds}
        sdo:
          - {{index: 0x2002, sub_index: 0, value: 1500}}
      scanner:
        node_id: 11
        dcf: {eds}
        product_code: 0x99
    """


def test_boots_are_shown_and_run_again_from_the_command_line(start_node, client_node,
                                                             tmp_path):
    group, port = private_bus()
    devices = [DurandDevice(node_id, 'udp_multicast', group, bus_options={'port': port})
               for node_id in (10, 11)]
    for device in devices:
        device.start()
    try:
        path = tmp_path / 'bus.yml'
        path.write_text(textwrap.dedent(BUS).format(eds=EDS))
        namespace = f'/boot{uuid.uuid4().hex[:8]}'
        process = start_node(['-r', f'__ns:={namespace}', '-p', 'can.interface:=udp_multicast',
                              '-p', f'can.channel:={group}', '-p', f'bus_config:={path}',
                              '-p', 'diagnostics_period:=0.2'], port)
        name = f'{namespace}/cbcan'
        boots, diagnostics = [], []
        client_node.create_subscription(BootStates, f'{name}/boot_states', boots.append,
                                        BOOT_STATES_QOS)
        client_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append,
                                        10)

        def latest():
            return {s.node_id: s for s in boots[-1].states} if boots else {}

        wait_until(lambda: latest().get(10) and latest()[10].state == 'BOOTED'
                   and latest().get(11) and latest()[11].state == 'FAILED', WAIT,
                   f'node 10 BOOTED, 11 FAILED on boot_states\n{process.output()}')
        assert devices[0].value(0x2002) == struct.pack('<I', 1500)
        assert (latest()[11].error_status, latest()[11].name) == ('M', 'scanner')

        def diagnosed():
            for array in diagnostics[-5:]:
                for status in array.status:
                    if status.name.endswith('node 11') and 'boot failed' in status.message:
                        return status
            return None
        status = wait_until(diagnosed, WAIT, 'node 11 boot failure on /diagnostics')
        assert status.level == b'\x02' and 'error M' in status.message, status
        values = {pair.key: pair.value for pair in status.values}
        assert values['Boot state'] == 'FAILED' and values['Boot error status'] == 'M'

        cli = [executable('cbcan_cli'), '--gateway', name, '--wait', str(START_TIMEOUT)]
        shown = subprocess.run(cli + ['boot-states'], capture_output=True, text=True,
                               timeout=120)
        assert shown.returncode == 0, shown.stderr
        rows = shown.stdout.splitlines()
        assert rows[1].split()[:6] == ['10', 'conveyor', 'BOOTED', '-', '1', '1'], rows
        assert rows[2].split()[:4] == ['11', 'scanner', 'FAILED', 'M'], rows

        devices[0].set_value(0x2002, 0, struct.pack('<I', 7))  # changed behind its back
        again = subprocess.run(cli + ['boot', '10'], capture_output=True, text=True,
                               timeout=120)
        assert again.returncode == 0, again.stderr
        assert again.stdout.splitlines()[1].split()[:6] == [
            '10', 'conveyor', 'BOOTED', '-', '1', '2'], again.stdout
        assert devices[0].value(0x2002) == struct.pack('<I', 1500)
        refused = subprocess.run(cli + ['boot', '11'], capture_output=True, text=True,
                                 timeout=120)
        assert refused.returncode == 1 and 'M product_code' in refused.stderr, refused.stderr
    finally:
        for device in devices:
            device.stop()
