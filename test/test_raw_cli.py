"""``cbcan_cli dump`` and ``cbcan_cli send`` against a gateway in this process, as users run them.

The other side of the bus is a python-can bus opened by this test: ``send`` must put
cansend's frames on it in order (or refuse all, exit 1), ``dump`` must print what it sends,
one line a frame, CANopen frames named as docs/raw_frames.md shows them.
"""

import re
import threading
import time

import can
from can_msgs.msg import Frame
import pytest

from cbcan_ros.ros.cli import build_parser, Client, run
from cbcan_ros.ros.cli.raw import canopen_name, describe_frame

from conftest import wait_until
from node_process import ROOT

PROMPT = 30.0


def cli(client, *arguments) -> int:
    return run(client, build_parser().parse_args(['--gateway', '/cbcan', *arguments]))


@pytest.fixture
def rig(make_gateway):
    """Yield (gateway, cbcan_cli client, another program's bus)."""
    gateway = make_gateway(raw__filters=['0:0', '18FF0000:1FFF0000'],
                           raw__send_allow=['7F0:7F0', '18FF5000:1FFFFF00'])
    client = Client('/cbcan', PROMPT)
    other = gateway.raw_bus()
    yield gateway, client, other
    other.shutdown()
    client.close()


def received(bus, ids, count):
    frames = []
    deadline = time.monotonic() + PROMPT
    while len(frames) < count and time.monotonic() < deadline:
        message = bus.recv(0.1)
        if message is not None and message.arbitration_id in ids:
            frames.append(message)
    return frames


def test_send_puts_cansend_frames_on_the_bus_in_order(rig, capsys):
    _gateway, client, other = rig
    assert cli(client, 'send', '7F0#DEADBEEF', '18FF5001#01.02.03', '7F1#R4', '7F2#') == 0
    assert capsys.readouterr().out == 'ok: 4 frames sent\n'
    frames = received(other, {0x7F0, 0x18FF5001, 0x7F1, 0x7F2}, 4)
    assert [(f.arbitration_id, f.is_extended_id, f.is_remote_frame, f.dlc, bytes(f.data))
            for f in frames] == [(0x7F0, False, False, 4, b'\xDE\xAD\xBE\xEF'),
                                 (0x18FF5001, True, False, 3, b'\x01\x02\x03'),
                                 (0x7F1, False, True, 4, b''), (0x7F2, False, False, 0, b'')]


def test_a_refused_send_exits_1_saying_why_and_sends_nothing(rig, capsys):
    _gateway, client, other = rig
    assert cli(client, 'send', '7F0#01', '6FF#05') == 1
    assert capsys.readouterr().err == (
        'error: frame 1 0x6FF: the id is not in parameter raw.send_allow; nothing was sent\n')
    assert cli(client, 'send', '7F3#03') == 0
    assert [frame.arbitration_id for frame in received(other, {0x7F0, 0x6FF, 0x7F3}, 1)] == \
        [0x7F3]


@pytest.mark.parametrize('frame', ['1234#00', '7F0#0', '7F0#001122334455667788', '7F0#R9',
                                   '7F0', '0x7F0#00', '7F0##100'])
def test_a_frame_cansend_would_not_take_is_refused_before_sending(rig, capsys, frame):
    _gateway, client, _other = rig
    assert cli(client, 'send', frame) == 2
    assert 'error: ' in capsys.readouterr().err


def test_dump_prints_one_line_a_frame_with_canopen_named(rig, capsys):
    gateway, client, other = rig
    status = []
    dumping = threading.Thread(target=lambda: status.append(
        cli(client, 'dump', '7F0:7F0', '18FF0000:1FFF0000', '#FFFFFFFF', '--count', '3')))
    dumping.start()
    wait_until(lambda: gateway.node.count_subscribers('/cbcan/from_can_bus') > 0, PROMPT,
               "dump's subscription")
    time.sleep(1.0)  # the subscription matched on the gateway's side too (DDS discovery)
    for frame in (dict(arbitration_id=0x185, data=b'\x01'),  # published, not shown
                  dict(arbitration_id=0x7F1, is_remote_frame=True, dlc=0),
                  dict(arbitration_id=0x18FF5001, is_extended_id=True, data=b'\x01\x02\x03'),
                  dict(arbitration_id=0x7F0, data=b'\xDE\xAD')):
        other.send(can.Message(**{'is_extended_id': False, **frame}))
    dumping.join(PROMPT)
    assert status == [0]
    assert capsys.readouterr().out.splitlines() == [
        '0x7F1 [0] remote request', '0x18FF5001 [3] 01 02 03', '0x7F0 [2] DE AD']

    status.clear()
    assert cli(client, 'dump', '700:780', '--count', '1') == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(r'0x70[235] \[1\] 7F  heartbeat node [235] PRE_OPERATIONAL', line), line


def test_dump_says_so_when_the_gateway_publishes_nothing(make_gateway, capsys):
    make_gateway()
    client = Client('/cbcan', PROMPT)
    try:
        assert cli(client, 'dump') == 2
    finally:
        client.close()
    assert capsys.readouterr().err == ('error: /cbcan publishes no raw frames: its parameter '
                                       'raw.filters is empty (["0:0"] publishes every '
                                       'standard frame)\n')


def _documented_lines():
    text = (ROOT / 'docs' / 'raw_frames.md').read_text()
    block = re.search(r'```text\n(0x705 \[1\] 7F  heartbeat node 5.*?)```', text, re.S)
    assert block, 'docs/raw_frames.md shows no dump output'
    return block.group(1).splitlines()


def test_the_dump_lines_the_documentation_shows_are_what_it_prints():
    frames = [Frame(id=0x705, dlc=1, data=[0x7F] + [0] * 7),
              Frame(id=0x585, dlc=8, data=[0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]),
              Frame(id=0x185, dlc=4, data=[0x34, 0x12, 0xFE, 0xFF, 0, 0, 0, 0]),
              Frame(id=0x085, dlc=8, data=[0x30, 0x81, 0x11, 0, 0, 0, 0, 0]),
              Frame(id=0x18FF5001, is_extended=True, dlc=3, data=[1, 2, 3, 0, 0, 0, 0, 0]),
              Frame(id=0x7F1, is_rtr=True, dlc=0)]
    assert [describe_frame(frame) for frame in frames] == _documented_lines()


@pytest.mark.parametrize('can_id, data, remote, name', [
    (0x000, b'\x01\x05', False, 'NMT START node 5'),
    (0x000, b'\x81\x00', False, 'NMT RESET_NODE node all'),
    (0x080, b'', False, 'SYNC'),
    (0x080, b'\x07', False, 'SYNC 7'),
    (0x100, bytes(6), False, 'TIME'),
    (0x081, b'\x00\x00\x00', False, 'EMCY node 1 0x0000 (error reset)'),
    (0x0FF, b'\x30\x81', False, 'EMCY node 127 0x8130'),
    (0x1FF, b'', False, 'TPDO1 node 127'),
    (0x205, b'', False, 'RPDO1 node 5'),
    (0x285, b'', False, 'TPDO2 node 5'),
    (0x505, b'', False, 'RPDO4 node 5'),
    (0x605, b'\x23\x02\x20\x00\x01\x00\x00\x00', False, 'SDO request node 5 write 0x2002:00'),
    (0x605, b'\x60\x00\x00\x00', False, 'SDO request node 5'),
    (0x585, b'\x60\x02\x20\x00', False, 'SDO answer node 5 write ok 0x2002:00'),
    (0x585, b'\x80\x00\x60\x00\x00\x00\x02\x06', False, 'SDO answer node 5 abort 0x06020000'),
    (0x705, b'\x05', False, 'heartbeat node 5 OPERATIONAL'),
    (0x705, b'\x00', False, 'heartbeat node 5 BOOT_UP'),
    (0x705, b'', True, 'node guarding request node 5'),
    (0x7E5, b'\x04\x01', False, 'LSS request'),
    (0x7E4, b'\x44', False, 'LSS answer'),
    (0x180, b'', False, ''),
    (0x7F0, b'', False, ''),
    (0x700, b'\x05', False, ''),
])
def test_canopen_frames_are_named_by_their_cob_id(can_id, data, remote, name):
    assert canopen_name(can_id, data, remote) == name
