"""Property-based tests of the drive support: its CiA 402 vocabulary, its checks, its service.

Generated with hypothesis:

* statuswords and controlword sequences against ``cia402`` (the gateway's reading of a drive)
  and the simulated drive's state machine (``simulation.cia402_states``, written apart):
  every statusword is one state, and the gateway's steps bring a drive from wherever it
  stands to OPERATION_ENABLED in at most four transitions, never out of a fault;
* any command, mode, timeout and value against ``drive_checks``: a check answers None or a
  message, and what the profile or the object cannot take is refused;
* any ``~/drive_command`` request against a live gateway (in this process) with a simulated
  drive: one answer each, the gateway keeps serving, and an answer that says "nothing was
  sent" is true on the bus.

Example counts are modest: the finite domains are checked whole instead.
"""

import logging
import math
import sys

import can
from hypothesis import event, given, HealthCheck, settings
from hypothesis import strategies as st
import pytest
from test_drives import NODE, Rig

from cbcan_ros.core.drives import cia402
from cbcan_ros.core.drives.checks import (
    command_problem,
    COMMANDS,
    integer_problem,
    MODES,
    request_problem,
    state_problem,
    value_problem,
)
from cbcan_ros.core.drives.status import DriveStatus
from cbcan_ros.core.sdo.requests import MAX_TIMEOUT
from cbcan_ros.simulation import cia402_states as sim

from conftest import wait_until

PURE = settings(max_examples=100, deadline=None, database=None)
LIVE = settings(max_examples=100, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

STATE_NAMES = [name for name, _, _ in cia402.STATES]
# Characters a ROS string carries (UTF-8, no NUL: the wire format ends strings at NUL).
TEXT = st.characters(blacklist_categories=('Cs',), blacklist_characters='\0')
MESSAGE_LIMIT = 1000  # a failure says why in a bounded message (core/text.py: never echo whole)


# Statuswords and the power state machine.

def test_every_statusword_shows_exactly_one_state():
    # All 65,536: each matches at most one (mask, value) of the profile, and state_of names
    # that one, or UNKNOWN when none matches.
    for statusword in range(0x10000):
        matching = [name for name, mask, value in cia402.STATES if statusword & mask == value]
        assert len(matching) <= 1, f'0x{statusword:04X} shows {matching}'
        assert cia402.state_of(statusword) == (matching[0] if matching else cia402.UNKNOWN)


@PURE
@given(state=st.sampled_from(list(sim.State)), other_bits=st.integers(0, 0xFFFF))
def test_the_gateway_reads_every_state_the_simulated_drive_shows(state, other_bits):
    # Whatever a drive sets besides the bits its state is read from (bit 5 in the states
    # that ignore it, voltage enabled, remote, target reached, the mode's bits 12 and 13,
    # manufacturer bits 14 and 15).
    mask = next(mask for name, mask, _ in cia402.STATES if name == state.name)
    assert cia402.state_of(state.value | other_bits & ~mask) == state.name


@PURE
@given(wanted=st.one_of(st.sampled_from([*STATE_NAMES, cia402.UNKNOWN]), st.text(TEXT)))
def test_no_step_is_sent_from_a_fault_or_a_state_the_drive_leaves_by_itself(wanted):
    # Only a fault reset leaves FAULT; the fault reaction and NOT_READY_TO_SWITCH_ON end by
    # themselves; UNKNOWN is no state to step from.
    for state in cia402.FAULTED | {cia402.UNKNOWN, cia402.NOT_READY_TO_SWITCH_ON}:
        assert cia402.step_towards(state, wanted) is None


def follow_steps(state: sim.State, wanted: str, quick_stop_option: int) -> list:
    """Follow step_towards(wanted) through the simulator's transitions; return the states.

    Stops at ``wanted``, at a state with no step, or after 8 steps.
    """
    passed = [state]
    while state.name != wanted and len(passed) <= 8:
        word = cia402.step_towards(state.name, wanted)
        if word is None:
            break
        following = sim.next_state(state, sim.command_of(word), quick_stop_option)
        assert following is not None, f'{state.name} does not take controlword 0x{word:04X}'
        state = following
        passed.append(state)
    return passed


def test_the_steps_reach_operation_enabled_from_every_state_in_4_transitions():
    # Every state and every quick stop option (0x605A) the simulated drive knows.
    for start in sim.State:
        for option in range(9):
            passed = follow_steps(start, cia402.OPERATION_ENABLED, option)
            names = [state.name for state in passed]
            if start.name in cia402.FAULTED | {cia402.NOT_READY_TO_SWITCH_ON}:
                assert passed == [start], names  # nothing to send: a reset, or wait
                continue
            assert passed[-1] is sim.State.OPERATION_ENABLED, names
            assert len(passed) - 1 <= 4, names


@PURE
@given(controlwords=st.lists(st.integers(0, 0xFFFF), max_size=12), option=st.integers(0, 8))
def test_after_any_controlwords_the_steps_enable_or_stop_the_drive(controlwords, option):
    # Wherever another master's controlwords left a drive: the enable path takes it to
    # OPERATION_ENABLED in at most 4 transitions, disable to SWITCH_ON_DISABLED in 1.
    state = sim.State.SWITCH_ON_DISABLED
    for word in controlwords:
        state = sim.next_state(state, sim.command_of(word), option) or state
    passed = follow_steps(state, cia402.OPERATION_ENABLED, option)
    assert passed[-1] is sim.State.OPERATION_ENABLED and len(passed) - 1 <= 4, passed
    passed = follow_steps(state, cia402.SWITCH_ON_DISABLED, option)
    assert passed[-1] is sim.State.SWITCH_ON_DISABLED and len(passed) - 1 <= 1, passed
    if state is sim.State.OPERATION_ENABLED:
        passed = follow_steps(state, cia402.QUICK_STOP_ACTIVE, option)
        assert passed == [state, sim.State.QUICK_STOP_ACTIVE], passed


# The checks.

COMMAND_TEXT = st.one_of(st.sampled_from([*COMMANDS, 'Enable', 'enable ', 'quick-stop', '']),
                         st.text(TEXT, max_size=20))
MODE_NUMBERS = st.one_of(st.sampled_from([0, *MODES, 2, 4, -1, -128, 127]),
                         st.integers(-128, 127))
TIMEOUTS = st.one_of(st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf, -1.0,
                                      MAX_TIMEOUT, math.nextafter(MAX_TIMEOUT, math.inf),
                                      5e-324, 1e300]),
                     st.floats(allow_nan=True, allow_infinity=True))


def acceptable_request(command: str, mode: int, timeout: float) -> bool:
    """Return whether a command request is well-formed, by the message's documentation."""
    return (command in ('enable', 'disable', 'quick_stop', 'halt', 'resume', 'fault_reset',
                        'set_mode', 'home')
            and (mode == 0 or mode in (1, 3, 4, 6, 8, 9, 10))
            and not (command == 'set_mode' and mode == 0)
            # below the smallest normal float: a Python int as rclpy sends it (values.py)
            and (timeout == 0 or sys.float_info.min <= timeout <= MAX_TIMEOUT))


@PURE
@given(command=COMMAND_TEXT, mode=MODE_NUMBERS, timeout=TIMEOUTS)
def test_a_request_is_refused_exactly_when_it_is_not_well_formed(command, mode, timeout):
    problem = request_problem(command, mode, timeout)
    assert problem is None or (isinstance(problem, str) and problem)
    assert (problem is None) == acceptable_request(command, mode, timeout), problem


def test_a_long_command_is_named_in_a_bounded_message():
    # Input is echoed cut short, never whole (core/text.py): a caller's 4,000-character
    # command must not come back as a 4,000-character message.
    problem = request_problem('x' * 4000, 0, 0.0)
    assert problem and len(problem) < MESSAGE_LIMIT, f'{len(problem)} characters'


STATUSES = st.builds(
    DriveStatus, node_id=st.integers(1, 127),
    state=st.sampled_from([*STATE_NAMES, cia402.UNKNOWN]), statusword=st.integers(0, 0xFFFF),
    mode=st.integers(-128, 127), error_code=st.integers(0, 0xFFFF),
    needs_enable=st.booleans(), supported_modes=st.integers(0, 0xFFFFFFFF))


@PURE
@given(status=STATUSES, heard=st.booleans(), enabled=st.booleans(), enabling=st.booleans())
def test_a_state_check_refuses_what_the_drive_cannot_take(status, heard, enabled, enabling):
    problem = state_problem(status, heard, enabled, enabling)
    takes = heard and status.state != cia402.UNKNOWN and (
        not enabled or (status.state == cia402.OPERATION_ENABLED and not status.needs_enable))
    assert (problem is None) == takes, problem
    if problem:
        assert f'node {status.node_id}' in problem
        if enabled and heard and status.faulted:
            assert 'fault_reset' in problem
        # An enable under way explains only a drive not enabled yet: not one lost or
        # faulted meanwhile (red team 19 saw "being enabled" of a drive in FAULT).
        being_enabled = (enabling and enabled and heard and status.state != cia402.UNKNOWN
                         and not status.faulted)
        assert ('is being enabled' in problem) == being_enabled, problem


@PURE
@given(status=STATUSES, command=COMMAND_TEXT, mode=MODE_NUMBERS)
def test_a_command_check_refuses_unsupported_modes_and_enabling_a_fault(status, command,
                                                                        mode):
    problem = command_problem(status, command, mode)
    wanted = cia402.HOMING if command == 'home' else mode  # home runs in homing, whatever mode
    unsupported = bool(wanted and status.supported_modes
                       and not cia402.supports(status.supported_modes, wanted))
    assert (problem is None) == (not unsupported
                                 and not (command == 'enable' and status.faulted)), problem
    assert problem is None or f'node {status.node_id}' in problem


@PURE
@given(value=st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300,
                                        2.0 ** 31, 2.0 ** 31 - 0.5, -2.0 ** 31 - 0.5,
                                        2.0 ** 15 - 0.5, -2.0 ** 15, 0.5, -0.5]),
                       st.floats(allow_nan=True, allow_infinity=True)),
       bits=st.sampled_from([16, 32]))
def test_a_target_is_refused_unless_it_is_finite_and_fits(value, bits):
    problem = value_problem('target', value, bits)
    fits = math.isfinite(value) and -(1 << bits - 1) <= round(value) < 1 << bits - 1
    assert (problem is None) == fits, problem
    if problem:
        assert problem.startswith('target ') and len(problem) < MESSAGE_LIMIT


@PURE
@given(value=st.integers(-(1 << 70), 1 << 70), bits=st.sampled_from([8, 16, 32]),
       unsigned=st.booleans())
def test_an_integer_fits_its_object_or_is_refused(value, bits, unsigned):
    problem = integer_problem('velocity', value, bits, unsigned)
    lowest = 0 if unsigned else -(1 << bits - 1)
    highest = (1 << bits) - 1 if unsigned else (1 << bits - 1) - 1
    assert (problem is None) == (lowest <= value <= highest), problem


# DriveCommand requests against a live gateway.

class Problems(logging.Handler):
    """Collects the gateway's log records of failures it did not expect."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.records = []

    def emit(self, record):
        """Keep ``record`` if it reports an unexpected failure."""
        text = record.getMessage()
        if (record.levelno >= logging.ERROR or 'unexpectedly' in text
                or 'handler failed' in text):
            self.records.append(text)


@pytest.fixture
def live(ros_context, start_durand):
    """One gateway with drive NODE (started, PDOs flowing) for all examples of a test."""
    problems = Problems()
    logger = logging.getLogger('cbcan_ros')
    logger.addHandler(problems)
    axis = Rig(start_durand)
    axis.problems = problems.records
    axis.bus = axis.gateway.raw_bus()
    yield axis
    axis.bus.shutdown()
    axis.close()
    logger.removeHandler(problems)


MARKER = bytes([0x40, 0x00, 0x10, 0x00])  # the SDO upload request of 0x1000:00


def frames_until_marker(axis) -> list:
    """Read node NODE's 0x1000 (a marker on the bus); return the frames before its request.

    Requests to one node go out one after another, and frames arrive in order: whatever
    the gateway sent the drive before (an RPDO, an SDO), it is among these.
    """
    read = axis.gateway.call('sdo_read', node_id=NODE, index=0x1000, subindex=0, timeout=5.0)
    assert read.success, f'the gateway stopped serving: {read.message}'
    frames = []

    def marker_seen():
        while True:
            message = axis.bus.recv(0)
            if message is None:
                return False
            if (message.arbitration_id == 0x600 + NODE
                    and bytes(message.data[:4]) == MARKER):
                return True
            frames.append(message)
    wait_until(marker_seen, 10.0, 'the marker request on the bus')
    return frames


def commanding(message: can.Message) -> bool:
    """Return whether a frame commands the drive: one of its RPDOs or an SDO download."""
    cob_id, data = message.arbitration_id, bytes(message.data)
    if cob_id in (0x200 + NODE, 0x300 + NODE, 0x400 + NODE, 0x500 + NODE):
        return True
    return cob_id == 0x600 + NODE and len(data) > 0 and data[0] >> 5 in (0, 1, 6)


LIVE_COMMANDS = st.one_of(st.sampled_from(COMMANDS), st.sampled_from(COMMANDS),
                          st.sampled_from(['Enable', 'enable ', 'quick-stop', '', 'stop']),
                          st.text(TEXT, max_size=20))
# Finite timeouts stay short, so a command that cannot finish answers soon.
LIVE_TIMEOUTS = st.one_of(st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf, -1.0,
                                           5e-324, 1e-3, MAX_TIMEOUT + 1e-9, 1e300]),
                          st.floats(-10.0, 10.0))
NODE_NUMBERS = st.one_of(st.just(NODE), st.just(NODE), st.integers(0, 255))
# Two in three requests are well-formed, so that the drive is enabled, stopped, halted, homed
# and switched between modes in between the refused ones.
WELL_FORMED = st.tuples(st.just(NODE), st.sampled_from(COMMANDS), st.sampled_from([0, *MODES]),
                        st.one_of(st.just(0.0), st.floats(1e-3, 5.0), st.just(5e-324)))
REQUESTS = st.one_of(WELL_FORMED, WELL_FORMED,
                     st.tuples(NODE_NUMBERS, LIVE_COMMANDS, MODE_NUMBERS, LIVE_TIMEOUTS))
ANSWER_MARGIN = 10.0  # past the request's own limit: what only a defect needs


@LIVE
@given(request=REQUESTS)
def test_any_drive_command_gets_one_honest_answer(live, request):
    node_id, command, mode, timeout = request
    frames_until_marker(live)  # what earlier examples sent is behind us
    limit = timeout if 0 < timeout <= MAX_TIMEOUT else 60.0 if command == 'home' else 2.0
    response = live.gateway.call('drive_command', wait=limit + ANSWER_MARGIN,
                                 node_id=node_id, command=command, mode=mode, timeout=timeout)
    sent = [m for m in frames_until_marker(live) if commanding(m)]
    event(f'{"succeeded" if response.success else "failed"}'
          f'{", sent" if sent else ""}: {response.message[:40]}')
    assert response.state in [*STATE_NAMES, cia402.UNKNOWN], response.state
    if not response.success:
        assert response.message, 'a failure without a message'
    well_formed = node_id == NODE and acceptable_request(command, mode, timeout)
    if not well_formed:
        assert not response.success
        assert 'nothing was sent' in response.message, response.message
        assert response.abort_code == 0, response.message
    if 'nothing was sent' in response.message:
        assert not sent, f'"{response.message}", yet the drive was sent: ' + ' '.join(
            f'{m.arbitration_id:03X}#{bytes(m.data).hex()}' for m in sent)
    assert live.problems == [], live.problems
    # The gateway keeps serving drive commands: one that always succeeds.
    answer = live.command('fault_reset')
    assert answer.success, answer.message
