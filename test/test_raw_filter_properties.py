"""Property-based tests of the raw CAN filters and send checks (hypothesis), without ROS.

- any filter string either parses or is refused with a ValueError naming the filter;
- a parsed filter lets a frame through exactly when candump's filter (as the kernel applies
  it to the frame's can_id with its EFF and RTR flags) matches it, among frames of the type
  the id's length names (1-3 digits standard, 8 extended);
- ``raw.send_allow`` never lets an id the gateway uses for CANopen through a wide entry: a
  frame is sent only when an entry matches it and, for a CANopen id, an entry with the full
  mask names that id; ``read_only`` refuses every frame; one refused frame in a call and the
  bus sees none of the call's frames.
"""

import re

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest

from cbcan_ros.core.bus import BusStatus
from cbcan_ros.core.raw.filters import parse_filters
from cbcan_ros.core.raw.frames import canopen_ids, FIXED_CANOPEN_IDS, Frame, RawFrames, RawSettings
from cbcan_ros.core.sdo.write_protection import WriteProtection

PROPERTIES = settings(max_examples=300, deadline=None, database=None,
                      suppress_health_check=[HealthCheck.too_slow])

CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
SERVED = (5, 6)  # devices of pdo.nodes in the send tests
NON_CANOPEN = 0x7F0  # no CANopen service of the gateway uses it


def candump_filter(text: str):
    """Return (can_id, can_mask, inverted, extended) as candump builds its can_filter."""
    inverted = '~' in text
    id_text, mask_text = re.split('[:~]', text)
    can_id, can_mask = int(id_text, 16), int(mask_text, 16) & ~CAN_ERR_FLAG
    extended = len(id_text) == 8
    if extended:
        can_id |= CAN_EFF_FLAG
    return can_id, can_mask, inverted, extended


def kernel_matches(text: str, frame_id: int, extended: bool, remote: bool) -> bool:
    """Return whether candump's filter ``text`` takes the frame (the kernel's rule).

    Restricted, as the gateway documents, to frames of the type the id's length names.
    """
    can_id, can_mask, inverted, filter_extended = candump_filter(text)
    if extended != filter_extended:
        return False
    received = frame_id | (CAN_EFF_FLAG if extended else 0) | (CAN_RTR_FLAG if remote else 0)
    return ((received & can_mask) == (can_id & can_mask)) != inverted


@st.composite
def filter_texts(draw):
    """Return one well-formed id filter as a robotics engineer would write it."""
    extended = draw(st.booleans())
    if extended:
        can_id = draw(st.integers(0, 0x1FFFFFFF))
        id_text = f'{can_id:08X}'
    else:
        can_id = draw(st.integers(0, 0x7FF))
        id_text = draw(st.sampled_from([f'{can_id:X}', f'{can_id:03X}', f'{can_id:03x}']))
    mask = draw(st.one_of(st.integers(0, 0xFFFFFFFF), st.sampled_from(
        [0, 0x7FF, 0x700, 0x780, 0x1FFFFFFF, 0x1FFF0000, 0x400007FF, 0xC00007FF])))
    mask_text = draw(st.sampled_from([f'{mask:X}', f'{mask:08X}']))
    return f'{id_text}{draw(st.sampled_from(":~"))}{mask_text}'


@st.composite
def frames_near(draw, texts):
    """Return (id, extended, remote): often an id the filters name, with bits flipped."""
    extended = draw(st.booleans())
    if texts and draw(st.booleans()):
        base = int(re.split('[:~]', draw(st.sampled_from(texts)))[0], 16)
        flips = draw(st.integers(0, 0x1FFFFFFF)) & draw(st.sampled_from([0, 1, 0x80, 0x7FF]))
        frame_id = base ^ flips
    else:
        frame_id = draw(st.integers(0, 0x1FFFFFFF))
    frame_id &= 0x1FFFFFFF if extended else 0x7FF
    return frame_id, extended, draw(st.booleans())


@PROPERTIES
@given(text=st.text(alphabet='0123456789abcdefABCDEFxXgj#:~, \t-', max_size=24))
def test_any_filter_string_parses_or_is_refused_naming_it(text):
    try:
        filters = parse_filters([text])
    except ValueError as error:
        assert any(repr(part.strip()[:40]) in str(error) for part in text.split(',')), error
        return
    for part in text.split(','):
        part = part.strip()
        assert not part or part in ('j', 'J') or part.startswith('#') or \
            re.fullmatch(r'[0-9A-Fa-f]{1,3}[:~][0-9A-Fa-f]{1,8}|[0-9A-Fa-f]{8}[:~][0-9A-Fa-f]{1,8}',
                         part), f'{part!r} was taken'
    assert len(filters.ids) == sum(1 for part in text.split(',') if part.strip() and
                                   part.strip() not in ('j', 'J') and
                                   not part.strip().startswith('#'))


@PROPERTIES
@given(data=st.data(), texts=st.lists(filter_texts(), min_size=1, max_size=4),
       join=st.booleans())
def test_frames_pass_exactly_when_candump_would_take_them(data, texts, join):
    filters = parse_filters(texts + (['j'] if join else []))
    for _ in range(20):
        frame_id, extended, remote = data.draw(frames_near(texts))
        verdicts = [kernel_matches(text, frame_id, extended, remote) for text in texts]
        expected = all(verdicts) if join else any(verdicts)
        assert filters.matches(frame_id, extended, remote, False) == expected, \
            (texts, hex(frame_id), extended, remote)


@PROPERTIES
@given(mask=st.integers(0, 0xFFFFFFFF), error_class=st.integers(0, 0x1FFFFFFF),
       texts=st.lists(filter_texts(), max_size=3))
def test_error_frames_pass_by_the_error_mask_only(mask, error_class, texts):
    filters = parse_filters(texts + [f'#{mask:X}'])
    expected = bool(mask) and (error_class == 0 or bool(error_class & mask))
    assert filters.matches(error_class, False, False, True) == expected
    assert not parse_filters(texts).matches(error_class, False, False, True)


class FakeBus:
    """The bus supervisor as the raw bridge uses it: up, and every frame sent kept."""

    def __init__(self):
        self.sent = []

    @property
    def status(self):
        """Return a bus that is up."""
        return BusStatus(True, '', 0, 0, 0, 0)

    def send(self, message):
        """Keep the frame as sent."""
        self.sent.append(message)

    def watch_frames(self, watcher, on_sent=None):
        """Receive nothing: only sending is tested here."""


class FakePdo:
    """The PDO service as canopen_ids reads it: TPDO 1 of node 5 moved to 0x1E5."""

    node_ids = list(SERVED)

    def mappings(self, node_id):
        """Return (TPDOs, RPDOs) of ``node_id``."""
        class Mapping:
            cob_id = 0x1E5

        return ({1: Mapping()}, {}) if node_id == 5 else ({}, {})


def bridge(send_allow, read_only=False):
    bus = FakeBus()
    raw = RawFrames(bus, RawSettings(send_allow=parse_filters(send_allow, errors=False)),
                    WriteProtection(read_only), lambda: canopen_ids(FakePdo()),
                    lambda: False)
    return raw, bus


PROTECTED = sorted(canopen_ids(FakePdo()))
wide_entries = st.sampled_from(['0:0', '600:700', '700:700', '000:780', '0~7F0', '080:780',
                                '180:7F', '7E0:7F0', '1E5:7FE', '00000000:00000000'])


def test_the_canopen_ids_include_the_served_devices_pdos_and_every_sdo():
    assert {0x000, 0x080, 0x100, 0x7E4, 0x7E5, 0x081, 0x0FF, 0x581, 0x5FF, 0x601, 0x67F,
            0x701, 0x77F}.issubset(FIXED_CANOPEN_IDS)
    assert {0x185, 0x205, 0x505, 0x186, 0x506, 0x1E5}.issubset(PROTECTED)
    assert 0x187 not in PROTECTED and NON_CANOPEN not in PROTECTED


@PROPERTIES
@given(entries=st.lists(st.one_of(wide_entries, filter_texts().filter(lambda t: ':' in t)),
                        min_size=1, max_size=4),
       frame_id=st.one_of(st.sampled_from(PROTECTED), st.integers(0, 0x7FF)),
       remote=st.booleans())
def test_a_canopen_id_is_sent_only_when_an_entry_names_it_with_the_full_mask(entries,
                                                                             frame_id, remote):
    raw, bus = bridge(entries)
    result = raw.send([Frame(frame_id, bytes(2), 2, is_rtr=remote)])
    allowed = any(kernel_matches(entry, frame_id, False, remote) for entry in entries)
    named = any(candump_filter(entry)[1] & 0x7FF == 0x7FF and not candump_filter(entry)[2] and
                not candump_filter(entry)[3] and int(re.split('[:~]', entry)[0], 16) == frame_id
                and kernel_matches(entry, frame_id, False, remote) for entry in entries)
    expected = allowed and (frame_id not in PROTECTED or named)
    assert result.success == expected, (entries, hex(frame_id), result.message)
    assert len(bus.sent) == result.sent == (1 if expected else 0)
    if not expected:
        assert f'0x{frame_id:03X}' in result.message
        assert ('raw.send_allow' in result.message), result.message


@PROPERTIES
@given(entries=st.lists(wide_entries, min_size=1, max_size=4),
       frame_id=st.sampled_from(PROTECTED))
def test_wide_entries_never_let_a_canopen_id_through(entries, frame_id):
    raw, bus = bridge(entries)
    assert not raw.send([Frame(frame_id, b'\x01', 1)]).success
    assert not bus.sent


@PROPERTIES
@given(ids=st.lists(st.integers(0, 0x7FF), min_size=1, max_size=20), bad=st.integers(0, 19),
       fault=st.sampled_from(['id', 'dlc', 'error', 'canopen']))
def test_one_refused_frame_and_none_of_the_call_is_sent(ids, bad, fault):
    raw, bus = bridge(['0:0'])
    frames = [Frame(frame_id, bytes(8), 8) for frame_id in ids if frame_id not in PROTECTED]
    if not frames:
        frames = [Frame(NON_CANOPEN, b'', 0)]
    bad %= len(frames)
    frames[bad] = {'id': Frame(0x800, b'', 0), 'dlc': Frame(NON_CANOPEN, bytes(9), 9),
                   'error': Frame(NON_CANOPEN, b'', 0, is_error=True),
                   'canopen': Frame(0x605, bytes(8), 8)}[fault]
    result = raw.send(frames)
    assert not result.success and result.sent == 0 and not bus.sent
    assert result.message.startswith(f'frame {bad} '), result.message
    assert raw.send([frame for i, frame in enumerate(frames) if i != bad]).success
    assert len(bus.sent) == len(frames) - 1


@pytest.mark.parametrize('entries', [['0:0'], ['605:7FF'], ['00000000:00000000']])
def test_read_only_refuses_every_frame(entries):
    raw, bus = bridge(entries, read_only=True)
    for frame in (Frame(NON_CANOPEN, b'', 0), Frame(0x605, b'', 0),
                  Frame(0x18FF0001, b'', 0, is_extended=True)):
        result = raw.send([frame])
        assert not result.success and 'read_only' in result.message
    assert not bus.sent


@pytest.mark.parametrize('text, problem', [
    ('0x123:7FF', 'hex without 0x'),
    ('1234:7FF', '4 digits'),
    ('FFF:7FF', 'above 7FF'),
    ('3FFFFFFF:1FFFFFFF', 'above 1FFFFFFF'),
    ('123', 'not id:mask'),
    ('123:', "mask ''"),
    ('#', "error mask ''"),
    ('12g:7FF', "id '12g'"),
])
def test_a_wrong_filter_is_refused_saying_why(text, problem):
    with pytest.raises(ValueError, match=re.escape(problem)) as raised:
        parse_filters(['0:0', f'{text}, 100:700'])
    assert repr(text) in str(raised.value)


def test_error_filters_and_join_are_refused_for_sending():
    for text in ('#FFFFFFFF', 'j'):
        with pytest.raises(ValueError, match='error frames cannot be sent'):
            parse_filters([text], errors=False)
