"""Property-based tests: random requests and random device answers never break the gateway.

Two kinds of input are generated with hypothesis:

* every field of every service request, across and beyond its range (within what the
  message type can carry): the answer always arrives within a bound, failures say why in a
  bounded message, and a known-good read still works afterwards (nothing escaped);
* the frames a rogue device (node ROGUE, no simulated device) answers a read or write with:
  proper answers, mutants of them and random frames near its COB-IDs. A small model of a
  CiA 301 client says, frame by frame, what each one means for the transfer; the gateway's
  answer, the requests it sends and its abort frames must agree with the model.

One gateway serves all examples of a test function (hypothesis reruns the body).
"""

from dataclasses import dataclass
import logging
import math
import re
import struct
import threading
import time
from typing import Optional

import can
from hypothesis import event, given, HealthCheck, Phase, settings
from hypothesis import strategies as st
import pytest

from cbcan_ros.core.sdo.abort_codes import WRITE_ONLY

from conftest import DEFAULT_DEVICES, wait_until

FUZZ = settings(max_examples=80, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])
# The rogue tests share a device channel whose state (late frames, what a failed transfer left
# behind) carries over between examples, so a shrunk example would not show the fault:
# they stop at the first failing example and report it as generated.
ROGUE_FUZZ = settings(FUZZ, max_examples=60, phases=[Phase.explicit, Phase.generate],
                      report_multiple_bugs=False)

SDO_TIMEOUT = 0.05  # the gateway's sdo.timeout: requests with timeout 0 to absent nodes
SHORT = 0.3  # longest timeout a fuzzed request to an absent node may wait
MARGIN = 2.0  # an answer's time past its request's timeout: milliseconds, on a quiet machine
MESSAGE_LIMIT = 1000
MAILBOX_MESSAGE_LIMIT = 8 * 250  # a multi SDO block reports up to 8 failures

DEVICE_TYPE = struct.pack('<I', 0x00020192)  # 0x1000 of every simulated device
KNOWN_STATES = {0: 'BOOT_UP', 4: 'STOPPED', 5: 'OPERATIONAL', 127: 'PRE_OPERATIONAL'}
STATE_NAME = re.compile(r'BOOT_UP|STOPPED|OPERATIONAL|PRE_OPERATIONAL|NOT_DETECTED|'
                        r'UNKNOWN_(\d+)')

ROGUE = 9
SDO_REQUEST = 0x600 + ROGUE
SDO_RESPONSE = 0x580 + ROGUE
MARKER_REQUEST = 0x605  # the known-good read goes to node 5
UNUSED_ID = 0x7F0  # no CANopen service uses it

TOGGLE_BIT = 0x05030000
TIMEOUT = 0x05040000
UNKNOWN_COMMAND = 0x05040001
DATA_TOO_LONG = 0x06070012
DATA_TOO_SHORT = 0x06070013


class Problems(logging.Handler):
    """Collects the gateway's log records of failures it did not expect."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.records = []

    def emit(self, record):
        """Keep ``record`` if it reports an unexpected failure."""
        text = record.getMessage()
        if 'unexpectedly' in text or 'handler failed' in text:
            self.records.append(text)


@pytest.fixture
def gateway(make_gateway):
    """One gateway for all examples of a test, with a short sdo.timeout."""
    problems = Problems()
    logger = logging.getLogger('cbcan_ros')
    logger.addHandler(problems)
    harness = make_gateway(sdo__timeout=SDO_TIMEOUT, heartbeat__timeout=60.0)
    harness.problems = problems.records
    yield harness
    logger.removeHandler(problems)


def timed_call(gateway, service: str, bound: float, **fields):
    """Call ``service``; fail unless the answer came within ``bound`` seconds."""
    started = time.monotonic()
    response = gateway.call(service, wait=bound + 5.0, **fields)
    elapsed = time.monotonic() - started
    assert elapsed <= bound, f'{service} answered after {elapsed:.2f} s (bound {bound:.2f} s)'
    return response


def assert_alive(gateway):
    """Check that a known-good read is still answered right and nothing unexpected logged."""
    response = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0, timeout=2.0)
    assert response.success, response.message
    assert bytes(response.data) == DEVICE_TYPE
    assert gateway.problems == [], gateway.problems


def assert_failure_message(response):
    """Check that a failure says why, in a bounded message."""
    assert response.message, f'a failure without a message: {response}'
    assert len(response.message) < MESSAGE_LIMIT, (
        f'a message of {len(response.message)} chars: {response.message[:200]}...')


def expected_state_name(state: int) -> str:
    """Return the name of a state byte a node reported (CiA 301 defines four)."""
    return KNOWN_STATES.get(state, f'UNKNOWN_{state}')


def assert_state_names(gateway):
    """Every node on the topic has a known state name or UNKNOWN_<n>, n not a known state."""
    latest = gateway.latest_states() or {}
    for node_id, name in latest.items():
        match = STATE_NAME.fullmatch(name)
        assert match, f'node {node_id} has state name {name!r}'
        if match.group(1) is not None:
            number = int(match.group(1))
            assert 0 <= number <= 127 and number not in KNOWN_STATES, name


# Service requests.

UINT8 = st.one_of(st.sampled_from([0, 1, 127, 128, 255]), st.integers(0, 0xFF))
UINT16 = st.one_of(st.sampled_from([0, 1, 0x7FFF, 0x8000, 0xFFFF]), st.integers(0, 0xFFFF))
UINT32 = st.one_of(st.sampled_from([0, 1, 3, 4, 5, 7, 0x7FFFFFFF, 0xFFFFFFFF]),
                   st.integers(0, 0xFFFFFFFF))
NODE_IDS = st.one_of(st.sampled_from([0, 1, 2, 3, 5, ROGUE, 127, 128, 255]), UINT8)
INDEXES = st.one_of(st.sampled_from([0x1000, 0x1008, 0x1017, 0x1018, 0x2000, 0x2002, 0x2003,
                                     0x2010, 0x2011, 0x2020, 0x2021, 0x2200]), UINT16)
# Every float32 (NaN, infinities, negatives, subnormals) rclpy lets a client send: it refuses
# the largest finite float32 itself, above its bound of 3.402823466e+38.
FLOAT32 = st.floats(width=32).filter(lambda t: not abs(t) > 3.402823466e+38 or math.isinf(t))
TIMEOUTS = st.one_of(st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf, -1.0, 60.0,
                                      60.000004, 1e30, -1e30]), FLOAT32)
DATA = st.one_of(st.binary(max_size=9), st.binary(max_size=4096))


def valid_timeout(timeout: float) -> bool:
    return not math.isnan(timeout) and 0.0 <= timeout <= 60.0


def reaches_bus(node_id: int) -> bool:
    return 1 <= node_id <= 127


def bounded_timeout(node_id: int, timeout: float) -> float:
    """Return ``timeout``, at most SHORT for a valid one to an absent node (short runs)."""
    if reaches_bus(node_id) and node_id not in DEFAULT_DEVICES and SHORT < timeout <= 60.0:
        return SHORT
    return timeout


def answer_bound(node_id: int, timeout: float) -> float:
    if not reaches_bus(node_id) or not valid_timeout(timeout):
        return MARGIN
    return (timeout or SDO_TIMEOUT) + MARGIN


@FUZZ
@given(node_id=NODE_IDS, index=INDEXES, subindex=UINT8, max_size=UINT32, timeout=TIMEOUTS)
def test_any_sdo_read_request_gets_one_honest_answer(gateway, node_id, index, subindex,
                                                     max_size, timeout):
    timeout = bounded_timeout(node_id, timeout)
    response = timed_call(gateway, 'sdo_read', answer_bound(node_id, timeout), node_id=node_id,
                          index=index, subindex=subindex, max_size=max_size, timeout=timeout)
    valid = node_id <= 127 and valid_timeout(timeout)
    if response.success:
        assert valid
        assert (response.abort_code, response.message) == (0, '')
        assert not max_size or len(response.data) <= max_size
        if node_id in DEFAULT_DEVICES and (index, subindex) == (0x1000, 0):
            assert bytes(response.data) == DEVICE_TYPE
    else:
        assert_failure_message(response)
        assert list(response.data) == []
        if not valid:
            assert response.abort_code == 0, response.message
        elif reaches_bus(node_id) and node_id not in DEFAULT_DEVICES:
            assert response.abort_code == TIMEOUT, response.message
    assert_alive(gateway)


@FUZZ
@given(node_id=NODE_IDS, index=INDEXES, subindex=UINT8, data=DATA, timeout=TIMEOUTS)
def test_any_sdo_write_request_gets_one_honest_answer(gateway, node_id, index, subindex,
                                                      data, timeout):
    if node_id in DEFAULT_DEVICES and index == 0x1017:
        index = 0x1016  # a 1 ms heartbeat of a simulated device would flood the shared bus
    timeout = bounded_timeout(node_id, timeout)
    response = timed_call(gateway, 'sdo_write', answer_bound(node_id, timeout),
                          node_id=node_id, index=index, subindex=subindex, data=list(data),
                          timeout=timeout)
    valid = node_id <= 127 and valid_timeout(timeout) and data
    if response.success:
        assert valid
        assert (response.abort_code, response.message) == (0, '')
        if node_id == 0 or node_id in DEFAULT_DEVICES:
            read = gateway.call('sdo_read', node_id=node_id, index=index, subindex=subindex,
                                timeout=10.0)
            if read.abort_code != WRITE_ONLY:  # a write-only object (0x2011) says so
                assert read.success, read.message
                assert bytes(read.data) == data, 'a successful write reads back'
    else:
        assert_failure_message(response)
        if not valid:
            assert response.abort_code == 0, response.message
        elif reaches_bus(node_id) and node_id not in DEFAULT_DEVICES:
            assert response.abort_code == TIMEOUT, response.message
    assert_alive(gateway)


@FUZZ
@given(node_id=NODE_IDS, command=st.one_of(st.sampled_from([1, 2, 128, 129, 130]), UINT8),
       state_node=NODE_IDS)
def test_any_nmt_request_gets_one_honest_answer(gateway, node_id, command, state_node):
    response = timed_call(gateway, 'nmt_command', MARGIN, node_id=node_id, command=command)
    valid = node_id <= 127 and command in (1, 2, 128, 129, 130)
    assert response.success == valid, response.message
    if not valid:
        assert_failure_message(response)
    state = timed_call(gateway, 'nmt_state', MARGIN, node_id=state_node)
    assert state.success == (1 <= state_node <= 127), state.message
    if not state.success:
        assert_failure_message(state)
    assert STATE_NAME.fullmatch(state.state_name), state.state_name
    assert_alive(gateway)


# PLC mailbox blocks.

WORD = st.integers(0, 0xFFFF)
MAILBOX_NODES = st.one_of(st.sampled_from([0, 2, 3, 5, ROGUE, 127, 128, 0xFFFF]), WORD)
MAILBOX_INDEXES = st.one_of(st.sampled_from([0x1000, 0x1008, 0x1018, 0x1F82, 0x2002, 0x2020,
                                             0x2021, 0x2200, 0x300C]), WORD)


@st.composite
def cbcan_blocks(draw):
    flag = draw(st.one_of(st.just(0xCA0E), WORD))
    command = draw(st.one_of(st.sampled_from([5055, 5066, 0x5055, 0x5066]), WORD))
    node = draw(MAILBOX_NODES)
    index = draw(MAILBOX_INDEXES)
    subindex = draw(st.one_of(st.sampled_from([0, 1, 2, 5, 127, 128, 129, 255, 256]), WORD))
    size = draw(st.one_of(st.integers(0, 129), WORD))
    data = draw(st.lists(WORD, min_size=64, max_size=64))
    return [flag, command, node, index, subindex, size] + data


@st.composite
def me3can_blocks(draw):
    command = draw(st.one_of(st.sampled_from([0x0004, 0x0006, 0x0008]), WORD))
    nodes = draw(st.one_of(st.just(st.sampled_from([0, 2, 3, 5, ROGUE])), st.just(MAILBOX_NODES)))
    entries = []
    for _ in range(8):
        node = draw(nodes)
        entries += [node, draw(MAILBOX_INDEXES), draw(WORD), draw(st.one_of(
            st.integers(0, 9), WORD))] + draw(st.lists(WORD, min_size=4, max_size=4))
    if command == 0x0004:
        return [command] + entries[:4] + [0] * 62
    return [command] + entries + [0, 0]


def harmless(block_format, registers):
    """Keep blocks from writing 0x1017 (a 1 ms heartbeat would flood the shared bus)."""
    registers = list(registers)
    if block_format in ('', 'cbcan') and len(registers) == 70 and registers[3] == 0x1017:
        registers[3] = 0x1016
    if block_format == 'me3can' and len(registers) == 67:
        for offset in range(1, 65, 8):
            if registers[offset + 1] == 0x1017:
                registers[offset + 1] = 0x1016
    return registers


# Characters a ROS string carries (UTF-8, no NUL: the wire format ends strings at NUL).
TEXT = st.characters(blacklist_categories=('Cs',), blacklist_characters='\0')
MAILBOX_REQUESTS = st.one_of(
    st.tuples(st.sampled_from(['', 'cbcan']), cbcan_blocks()),
    st.tuples(st.just('me3can'), me3can_blocks()),
    st.tuples(st.one_of(st.sampled_from(['', 'cbcan', 'me3can', 'CBCAN', 'cbcan ', ' me3can']),
                        st.text(TEXT, max_size=30), st.text(TEXT, min_size=1000, max_size=4000)),
              st.lists(WORD, max_size=200)),
)


@FUZZ
@given(request=MAILBOX_REQUESTS)
def test_any_mailbox_block_gets_one_honest_answer(gateway, request):
    block_format, registers = request
    registers = harmless(block_format, registers)
    bound = 8 * SDO_TIMEOUT + 0.4 + MARGIN  # up to 8 accesses; a slow 0x2200 read ends late
    response = timed_call(gateway, 'plc_mailbox', bound, format=block_format,
                          registers=registers)
    answer, message = list(response.registers), response.message
    assert len(message) < MAILBOX_MESSAGE_LIMIT, f'{len(message)} chars: {message[:200]}...'
    assert len(answer) == len(registers), 'the block keeps its length'
    known = block_format in ('', 'cbcan', 'me3can')
    length = 67 if block_format == 'me3can' else 70
    if not known or len(registers) != length:
        assert answer == registers and message, 'a block of no format comes back unchanged'
    elif block_format == 'me3can':
        assert answer[0] in (0x0005, 0x0007, 0x0009, 0x000F, 0x00F7, 0x00F9), answer[0]
        failed = answer[0] in (0x000F, 0x00F7, 0x00F9)
        assert bool(message) == failed, (answer[0], message)
    elif registers[0] != 0xCA0E:
        assert answer == registers and message, 'nothing runs without the execute flag'
    else:
        assert answer[0] in (0, 1, 2, 4), answer[0]
        assert answer[1:5] == registers[1:5], 'command, node, index, subindex are kept'
        assert bool(message) == (answer[0] != 0), (answer[0], message)
    assert_alive(gateway)


# A rogue device answering with random frames.

def sdo(command: int, index: int = 0, subindex: int = 0, payload: bytes = b'') -> bytes:
    """Return an 8-byte SDO frame: command, multiplexer, payload (zero padded)."""
    return (struct.pack('<BHB', command, index, subindex) + payload).ljust(8, b'\x00')


def segment_frame(command: int, data: bytes) -> bytes:
    return (bytes([command]) + data).ljust(8, b'\x00')


@dataclass(frozen=True)
class Outcome:
    """How a transfer ends: success with data, or failure with a code."""

    success: bool
    data: bytes = b''
    code: int = 0
    gateway_aborts: bool = False  # the client (gateway) must send an abort frame


class Model:
    """A CiA 301 SDO client's view of one transfer (expedited and segmented, no block).

    ``on_frame`` says whether a frame ends the current step: an answer that the client acts
    on (next request or the end), an abort, or a protocol error the client aborts for.
    Frames that answer nothing asked (other objects, shorter than 8 bytes, other COB-IDs,
    extended or remote frames) are ignored.
    """

    def __init__(self, write: bool, index: int, subindex: int, data: bytes = b''):
        self.write = write
        self.mux = (index, subindex)
        self.data = data
        self.initiating = True
        self.toggle = 0
        self.position = 0  # download: bytes acknowledged
        self.received = b''  # upload: bytes received
        self.announced: Optional[int] = None
        self.outcome: Optional[Outcome] = None

    def request(self) -> bytes:
        """Return the request the client sends next."""
        index, subindex = self.mux
        if self.initiating:
            if not self.write:
                return sdo(0x40, index, subindex)
            if len(self.data) <= 4:
                return sdo(0x23 | (4 - len(self.data)) << 2, index, subindex, self.data)
            return sdo(0x21, index, subindex, struct.pack('<I', len(self.data)))
        if not self.write:
            return segment_frame(0x60 | self.toggle << 4, b'')
        chunk = self.data[self.position:self.position + 7]
        last = self.position + len(chunk) >= len(self.data)
        return segment_frame(self.toggle << 4 | (7 - len(chunk)) << 1 | last, chunk)

    def proper(self, payload: bytes, mode: str) -> bytes:
        """Return the answer a correct device holding ``payload`` gives now."""
        index, subindex = self.mux
        if self.initiating:
            if self.write:
                return sdo(0x60, index, subindex)
            if mode == 'expedited' and 1 <= len(payload) <= 4:
                return sdo(0x43 | (4 - len(payload)) << 2, index, subindex, payload)
            if mode == 'expedited_unsized' and len(payload) == 4:
                return sdo(0x42, index, subindex, payload)
            if mode == 'segmented_unsized':
                return sdo(0x40, index, subindex)
            return sdo(0x41, index, subindex, struct.pack('<I', len(payload)))
        if self.write:
            return segment_frame(0x20 | self.toggle << 4, b'')
        chunk = payload[len(self.received):len(self.received) + 7]
        last = len(self.received) + len(chunk) >= len(payload)
        return segment_frame(self.toggle << 4 | (7 - len(chunk)) << 1 | last, chunk)

    def on_frame(self, message: can.Message) -> bool:
        """Feed a frame the rogue sent; return True when it ends the current step."""
        data = bytes(message.data)
        if (message.arbitration_id != SDO_RESPONSE or message.is_extended_id
                or message.is_remote_frame or len(data) < 8):
            return False
        command = data[0]
        frame_mux = struct.unpack_from('<HB', data, 1)
        if command == 0x80:
            if self.initiating and frame_mux not in (self.mux, (0, 0)):
                return False  # an abort of an earlier transfer
            return self._end(False, code=struct.unpack_from('<I', data, 4)[0])
        if self.initiating:
            return self._initiation(command, frame_mux, data)
        if command & 0xE0 != (0x20 if self.write else 0x00):
            return self._end(False, code=UNKNOWN_COMMAND, gateway_aborts=True)
        if command & 0x10 != self.toggle << 4:
            return self._end(False, code=TOGGLE_BIT, gateway_aborts=True)
        self.toggle ^= 1
        if self.write:
            self.position += len(self.data[self.position:self.position + 7])
            if self.position >= len(self.data):
                return self._end(True)
            return True
        self.received += data[1:8 - (command >> 1 & 7)]
        if self.announced is not None and len(self.received) > self.announced:
            return self._end(False, code=DATA_TOO_LONG, gateway_aborts=True)
        if command & 0x01:
            if self.announced is not None and len(self.received) != self.announced:
                return self._end(False, code=DATA_TOO_SHORT, gateway_aborts=True)
            return self._end(True, self.received)
        return True

    def _initiation(self, command: int, frame_mux, data: bytes) -> bool:
        if frame_mux != self.mux:
            return False  # an answer about another object
        if self.write:
            if command != 0x60:
                return False
            if len(self.data) <= 4:
                return self._end(True)
            self.initiating = False
            return True
        if command & 0xE0 != 0x40:
            return False
        if command & 0x02:  # expedited
            size = 4 - (command >> 2 & 3) if command & 0x01 else 4
            return self._end(True, data[4:4 + size])
        self.announced = struct.unpack_from('<I', data, 4)[0] if command & 0x01 else None
        self.initiating = False
        return True

    def _end(self, success: bool, data: bytes = b'', code: int = 0,
             gateway_aborts: bool = False) -> bool:
        self.outcome = Outcome(success, bytes(data), code, gateway_aborts)
        return True


NEAR_IDS = st.sampled_from([SDO_RESPONSE, SDO_RESPONSE, SDO_RESPONSE - 1, SDO_RESPONSE + 1,
                            SDO_REQUEST, 0x700 + ROGUE, 0x080 + ROGUE, 0x180 + ROGUE,
                            0x500 + ROGUE])
MUTATIONS = ['command', 'flip', 'mux', 'truncate', 'id', 'extended', 'remote', 'payload',
             'toggle', 'size_bits', 'size']
PROPER = ('proper', None, None, b'')
MUTANT_PLANS = st.tuples(st.just('mutant'), st.sampled_from(MUTATIONS),
                         st.integers(0, 0xFFFFFFFF), st.binary(min_size=8, max_size=8))
ABORT_PLANS = st.tuples(st.just('abort'), st.sampled_from(['own', 'zero', 'other']),
                        st.one_of(st.sampled_from([0, 0x05040000, 0x06020000, 0x08000000]),
                                  st.integers(0, 0xFFFFFFFF)), st.just(b''))
FRAME_PLANS = st.one_of(
    st.just(PROPER),
    MUTANT_PLANS,
    ABORT_PLANS,
    st.tuples(st.just('random'), NEAR_IDS, st.integers(0, 0xFFFFFFFF),
              st.binary(max_size=8)),
)
# How a step ends after its frames: mostly the proper answer, sometimes nothing (a timeout),
# an abort or a mutant of the proper answer.
ENDINGS = st.integers(0, 19).flatmap(
    lambda n: st.just(PROPER) if n < 14 else st.none() if n < 15
    else ABORT_PLANS if n < 17 else MUTANT_PLANS)
STEP_PLANS = st.tuples(st.lists(FRAME_PLANS, max_size=3), ENDINGS)
MUXES = [(0, 0), (0x2002, 0), (0x2002, 1), (0x2003, 0), (0xFFFF, 0xFF)]


def materialize(plan, proper: bytes, own_mux) -> can.Message:
    """Turn one frame plan into the frame the rogue sends."""
    kind, choice, value, data = plan
    if kind == 'proper':
        return can.Message(arbitration_id=SDO_RESPONSE, data=proper, is_extended_id=False)
    if kind == 'abort':
        index, subindex = {'own': own_mux, 'zero': (0, 0), 'other': (0x2003, 7)}[choice]
        return can.Message(arbitration_id=SDO_RESPONSE, is_extended_id=False,
                           data=sdo(0x80, index, subindex, struct.pack('<I', value)))
    if kind == 'random':
        return can.Message(arbitration_id=choice, data=data, is_extended_id=value & 1 == 1)
    frame = bytearray(proper)
    arbitration_id, extended, remote = SDO_RESPONSE, False, False
    if choice == 'command':
        frame[0] = value & 0xFF
    elif choice == 'flip':
        frame[0] ^= 1 << (value % 8)
    elif choice == 'mux':
        index, subindex = MUXES[value % len(MUXES)]
        struct.pack_into('<HB', frame, 1, index, subindex)
    elif choice == 'truncate':
        frame = frame[:value % 8]
    elif choice == 'id':
        arbitration_id = [SDO_RESPONSE - 1, SDO_RESPONSE + 1, SDO_REQUEST, 0x585,
                          0x700 + ROGUE][value % 5]
    elif choice == 'extended':
        extended = True
    elif choice == 'remote':
        remote = True
    elif choice == 'payload':
        frame[1:] = data[1:]
    elif choice == 'toggle':
        frame[0] ^= 0x10
    elif choice == 'size':
        frame[4:8] = struct.pack('<I', value % 40)
    elif choice == 'size_bits':
        frame[0] = frame[0] & 0xF1 | (value % 8) << 1
    if remote:
        return can.Message(arbitration_id=arbitration_id, is_remote_frame=True,
                           dlc=len(frame), is_extended_id=extended)
    return can.Message(arbitration_id=arbitration_id, data=bytes(frame),
                       is_extended_id=extended)


class RogueDevice:
    """Node ROGUE on the raw bus, answering each request of an armed transfer by its plan.

    It records every frame the gateway sends to 0x600+ROGUE and the marker read's request
    (0x605), so the frames of one example are known completely once the marker is seen.
    """

    def __init__(self, gateway):
        self.bus = gateway.raw_bus()
        self.log = []
        self.problems = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.model: Optional[Model] = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def arm(self, model: Model, steps, payload: bytes, mode: str) -> int:
        """Play ``steps`` for the transfer ``model`` describes; return the log position."""
        with self._lock:
            self.model, self.steps, self.payload, self.mode = model, list(steps), payload, mode
            self.requests = []
            self.problems = []
            return len(self.log)

    def frames_since(self, position: int):
        """Return the frames logged from ``position`` on: (sender, COB-ID, data)."""
        with self._lock:
            return list(self.log[position:])

    def _run(self):
        while not self._stop.is_set():
            message = self.bus.recv(0.02)
            if message is None or message.arbitration_id not in (SDO_REQUEST, MARKER_REQUEST):
                continue
            with self._lock:
                self.log.append(('gateway', message.arbitration_id, bytes(message.data)))
            if message.arbitration_id != SDO_REQUEST or message.data[0] == 0x80:
                continue
            try:
                self._answer(bytes(message.data))
            except Exception as error:  # noqa: BLE001 - reported by the test
                self.problems.append(repr(error))

    def _answer(self, request: bytes):
        model = self.model
        if model is None or model.outcome is not None:
            self.problems.append(f'request {request.hex()} after the transfer ended')
            return
        expected = model.request()
        self.requests.append(request)
        if request != expected:
            self.problems.append(f'request {request.hex()}, expected {expected.hex()}')
            return
        frames, ending = self.steps.pop(0) if self.steps else ([], PROPER)
        plans = list(frames) + ([] if ending is None else [ending])
        for plan in plans:
            message = materialize(plan, model.proper(self.payload, self.mode), model.mux)
            self.bus.send(message)
            with self._lock:
                self.log.append(('rogue', message.arbitration_id, bytes(message.data)))
            if model.on_frame(message):
                return  # the step is over: nothing more is sent for this request

    def close(self):
        """Stop the rogue and close its bus."""
        self._stop.set()
        self._thread.join(5.0)
        self.bus.shutdown()


@pytest.fixture
def rogue(gateway):
    device = RogueDevice(gateway)
    yield device
    device.close()


def check_transfer(gateway, rogue, model: Model, position: int, response, elapsed: float,
                   timeout: float):
    """Compare the gateway's answer and frames with the model's."""
    assert elapsed <= timeout + MARGIN, f'answered after {elapsed:.2f} s, timeout {timeout} s'
    assert_alive(gateway)  # its request to node 5 is the marker in the rogue's log
    wait_until(lambda: any(arbitration_id == MARKER_REQUEST
                           for _, arbitration_id, _ in rogue.frames_since(position)),
               5.0, 'the marker request')
    frames = rogue.frames_since(position)
    frames = frames[:[arbitration_id for _, arbitration_id, _ in frames].index(MARKER_REQUEST)]
    trace = (f'\nframes (sender, COB-ID, data): '
             f'{[(who, hex(cob), data.hex()) for who, cob, data in frames]}'
             f'\nanswer: {response}')
    assert rogue.problems == [], f'{rogue.problems}{trace}'
    outcome = model.outcome or Outcome(False, code=TIMEOUT, gateway_aborts=True)
    event('success' if outcome.success else f'0x{outcome.code:08X}')
    if outcome.success:
        assert response.success, f'expected success{trace}'
        assert (response.abort_code, response.message) == (0, ''), trace
        if not model.write:
            assert bytes(response.data) == outcome.data, f'success with other data{trace}'
    else:
        assert not response.success, f'success where the model says 0x{outcome.code:08X}{trace}'
        assert response.abort_code == outcome.code, f'expected 0x{outcome.code:08X}{trace}'
        assert response.message.startswith(f'0x{outcome.code:08X}'), trace
        assert len(response.message) < MESSAGE_LIMIT, trace
        if not model.write:
            assert list(response.data) == [], trace
    ours = [data for who, cob, data in frames if who == 'gateway' and cob == SDO_REQUEST]
    aborts = [data for data in ours if data[0] == 0x80]
    if outcome.gateway_aborts:
        index, subindex = model.mux
        assert aborts == [sdo(0x80, index, subindex, struct.pack('<I', outcome.code))], (
            f'wrong abort frames{trace}')
        assert ours[-1][0] == 0x80, f'something was sent after the abort{trace}'
    else:
        assert aborts == [], f'abort frames though none was due{trace}'


READ_MODES = st.sampled_from(['expedited', 'expedited_unsized', 'segmented_sized',
                              'segmented_unsized'])
ROGUE_TIMEOUT = 0.25


@ROGUE_FUZZ
@given(payload=st.binary(max_size=24), mode=READ_MODES, steps=st.lists(STEP_PLANS, max_size=5),
       target=st.sampled_from([(0x2002, 0), (0x1008, 0), (0x1018, 4)]))
def test_rogue_answers_to_a_read_never_give_wrong_data(gateway, rogue, payload, mode, steps,
                                                       target):
    model = Model(False, *target)
    position = rogue.arm(model, steps, payload, mode)
    started = time.monotonic()
    response = gateway.call('sdo_read', wait=ROGUE_TIMEOUT + 2.0, node_id=ROGUE,
                            index=target[0], subindex=target[1], timeout=ROGUE_TIMEOUT)
    check_transfer(gateway, rogue, model, position, response, time.monotonic() - started,
                   ROGUE_TIMEOUT)
    assert_state_names(gateway)


@ROGUE_FUZZ
@given(data=st.one_of(st.binary(min_size=1, max_size=4), st.binary(min_size=5, max_size=30)),
       steps=st.lists(STEP_PLANS, max_size=6),
       target=st.sampled_from([(0x2002, 0), (0x2021, 0), (0x1018, 4)]))
def test_rogue_answers_to_a_write_never_fake_success(gateway, rogue, data, steps, target):
    model = Model(True, *target, data=data)
    position = rogue.arm(model, steps, b'', '')
    started = time.monotonic()
    response = gateway.call('sdo_write', wait=ROGUE_TIMEOUT + 2.0, node_id=ROGUE,
                            index=target[0], subindex=target[1], data=list(data),
                            timeout=ROGUE_TIMEOUT)
    check_transfer(gateway, rogue, model, position, response, time.monotonic() - started,
                   ROGUE_TIMEOUT)
    assert_state_names(gateway)


# Heartbeats with state bytes CiA 301 does not define.

HEARTBEAT_NODES = st.sampled_from([1, 4, ROGUE, 10, 64, 126, 127])


@FUZZ
@given(frames=st.lists(st.tuples(HEARTBEAT_NODES, st.one_of(
    st.binary(max_size=8), st.sampled_from([b'\x00', b'\x04', b'\x05', b'\x06', b'\x7f',
                                            b'\x80', b'\x85', b'\xff', b'\x01\x02'])),
), min_size=1, max_size=8))
def test_heartbeats_with_any_state_byte_are_named_honestly(gateway, frames):
    # The gateway lives across examples: its states may show this example's names before it
    # heard these frames. A marker after them, handed on in order, says they all arrived.
    handed_on = threading.Event()
    network = gateway.node.gateway.network
    network.subscribe(UNUSED_ID, lambda *_frame: handed_on.set())
    bus = gateway.raw_bus()
    try:
        for node_id, data in frames:
            bus.send(can.Message(arbitration_id=0x700 + node_id, data=data,
                                 is_extended_id=False))
        bus.send(can.Message(arbitration_id=UNUSED_ID, data=b'', is_extended_id=False))
        wait_until(handed_on.is_set, 10.0, 'the frames handed on to the gateway')
    finally:
        bus.shutdown()
        network.unsubscribe(UNUSED_ID)
    expected = {}
    for node_id, data in frames:
        if data:
            expected[node_id] = data[0] & 0x7F
    names = {node_id: expected_state_name(state) for node_id, state in expected.items()}

    def shown():
        latest = gateway.latest_states() or {}
        return all(latest.get(node_id) in ((names[node_id], 'NOT_DETECTED') if state == 6
                                           else (names[node_id],))
                   for node_id, state in expected.items())
    wait_until(shown, 10.0, f'states {names} on the topic (seen {gateway.latest_states()})')
    assert_state_names(gateway)
    for node_id, state in expected.items():
        answer = gateway.call('nmt_state', node_id=node_id)
        assert answer.success and answer.state == state, answer
        if state != 6:  # 6 has a test of its own below
            assert answer.state_name == names[node_id], answer
        assert 0.0 <= answer.last_seen_age < 5.0, answer


def test_a_heard_node_reporting_state_6_is_not_shown_as_not_detected(gateway):
    """CiA 301 defines heartbeat states 0, 4, 5 and 127; 6 is the gateway's NOT_DETECTED.

    A node that sends heartbeats is detected: its undefined state byte 6 must be shown as
    UNKNOWN_6, not as NOT_DETECTED (which says the node is silent).
    """
    bus = gateway.raw_bus()
    try:
        bus.send(can.Message(arbitration_id=0x700 + ROGUE, data=b'\x06', is_extended_id=False))
    finally:
        bus.shutdown()
    answer = wait_until(lambda: (lambda a: a if a.last_seen_age >= 0 else None)(
        gateway.call('nmt_state', node_id=ROGUE)), 5.0, 'the heartbeat of the rogue')
    assert answer.state_name == 'UNKNOWN_6', (
        f'a node heard {answer.last_seen_age:.2f} s ago is named {answer.state_name}')
    gateway.wait_for_states({ROGUE: 'UNKNOWN_6'})
