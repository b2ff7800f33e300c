"""Bus faults with the installed ``cbcan_node`` as a separate process.

A robot's USB-CAN adapter speaks slcan: here python-can's real ``slcan`` driver in the node
talks to a fake adapter on a pseudo-terminal (test/fake_slcan.py), which is unplugged and
plugged back.
"""

from cbcan_ros.simulation.canopen_device import SimulatedDevice
from cbcan_ros.srv import SdoRead, SdoWrite

from conftest import HEAVY, new_channel, wait_for_future, wait_until
from fake_slcan import FakeSlcanAdapter
from node_process import arguments, call, EDS, namespace, service_client, StateWatcher

# Reopening backs off up to 5 s between attempts; with room for a loaded machine.
RECOVERY = 20.0
ANSWER = 10.0  # ceiling for an answer that comes at once, or within a short timeout
DOMAIN = 0x2020  # the durand device's large DOMAIN (64 KiB)
BIG = bytes(i * 7 & 0xFF for i in range(65536))


def test_slcan_adapter_plugged_in_late_unplugged_and_plugged_back(
        start_node, client_node, tmp_path):
    channel = new_channel()
    device = SimulatedDevice(2, EDS, 'virtual', channel)
    device.start()
    link = tmp_path / 'usb-can0'
    adapter = FakeSlcanAdapter(link, channel, plugged=False)
    name = f'{namespace()}/cbcan'
    try:
        gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                              '-p', 'can.interface:=slcan', '-p', f'can.channel:={link}',
                              '-p', 'can.bitrate:=500000',
                              '-p', 'can.options:=[sleep_after_open=0]',
                              '-p', 'nodes:=[2]', '-p', 'heartbeat.timeout:=0.5',
                              '-p', 'state_publish_period:=0.1'])
        states = StateWatcher(client_node, name)
        sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
        request = SdoRead.Request(node_id=2, index=0x1000, subindex=0)

        # Started before the adapter was plugged in: honest errors, no exit.
        answer = call(sdo_read, request, 'sdo_read before the adapter is plugged in', gateway)
        assert not answer.success
        assert 'CAN bus is down' in answer.message and 'cannot open' in answer.message
        assert gateway.process.poll() is None

        adapter.plug()
        wait_until(lambda: wait_for_future(sdo_read.call_async(request), ANSWER).success,
                   RECOVERY, 'SDO through the adapter once plugged in')
        states.wait_for({2: 'PRE_OPERATIONAL'}, RECOVERY)

        adapter.unplug()
        states.wait_for({2: 'NOT_DETECTED'}, ANSWER)
        answer = wait_for_future(sdo_read.call_async(request), ANSWER)
        assert not answer.success and 'CAN bus is down' in answer.message, answer.message

        adapter.plug()
        wait_until(lambda: wait_for_future(sdo_read.call_async(request), ANSWER).success,
                   RECOVERY, 'SDO again after the adapter came back')
        states.wait_for({2: 'PRE_OPERATIONAL'}, RECOVERY)
        assert bytes(wait_for_future(sdo_read.call_async(request), ANSWER).data) == bytes(
            [0x92, 0x01, 0x02, 0x00])
        gateway.stop()
        output = gateway.output()
        assert gateway.process.returncode == 0, output
        # One line per fault: the first failed open and the unplug, not one per attempt.
        assert output.count('is down') == 2, output
        assert output.count('up again') == 1, output
    finally:
        adapter.close()
        device.stop()


# "Logs the fault once (not once per frame or attempt)".

@HEAVY
def test_unplug_during_block_download_logs_the_fault_only_once(
        start_node, client_node, durand_device, tmp_path):
    # Once a defect: canopen's BlockDownloadStream.close() logged "Block transfer was not
    # finished" through Python's last-resort handler, a second line for the one fault.
    channel = new_channel()
    durand_device('virtual', channel)
    link = tmp_path / 'usb-can'
    adapter = FakeSlcanAdapter(link, channel)
    name = f'{namespace()}/cbcan'
    try:
        gateway = start_node(arguments(name, '-p', 'can.interface:=slcan',
                                       '-p', f'can.channel:={link}',
                                       '-p', 'can.options:=[sleep_after_open=0]',
                                       '-p', 'sdo.block_transfer:=true'))
        sdo_write = service_client(client_node, SdoWrite, f'{name}/sdo_write', gateway)
        call = sdo_write.call_async(SdoWrite.Request(node_id=2, index=DOMAIN, data=BIG,
                                                     timeout=30.0))
        wait_until(lambda: adapter.frames_to_bus > 150, 30.0, 'the block download under way')
        adapter.unplug()
        answer = wait_for_future(call, ANSWER)  # at once, long before its 30 s timeout
        assert not answer.success and 'CAN bus is down' in answer.message, answer.message
        gateway.stop()
    finally:
        adapter.close()
    output = gateway.output()
    assert gateway.process.returncode == 0, output
    assert output.count('is down') == 1, output
    stray = [line for line in output.splitlines() if line and not line.startswith('[')]
    assert stray == [], output
