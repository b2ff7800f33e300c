"""What the drive applies after a stop, on synchronous RPDOs that all carry the controlword.

The 'vendor' layout (Maxon EPOS2 and the like: the controlword in each of the four RPDOs)
with every RPDO synchronous, the gateway producing SYNC: the drive keeps the last frame each
RPDO received and applies it at the next SYNC. A robot program streams velocity targets,
then the drive is stopped (quick_stop, halt, the command timeout, SIGINT). What counts is
what the durand drive APPLIED, over time: after a quick stop it never goes back to
OPERATION_ENABLED (its quick stop option 6 keeps it in QUICK_STOP_ACTIVE, where a
controlword "enable operation" is transition 16 and runs it again), after a halt it never
applies a controlword without the halt bit, nor moves again, without a fresh command.
"""

from dataclasses import replace
import signal
import struct
import threading
import time

from lifecycle_msgs.msg import Transition
import pytest
from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    configure_once_read,
    CSV,
    HALT,
    MANAGED,
    managed_transition,
    NODE,
    rig,
    stop_with,
    VELOCITY,
)

from cbcan_ros.simulation.durand.drive_objects import QUICK_STOP_OPTION
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos

from conftest import wait_until

SYNC = 0x80
STAY_IN_QUICK_STOP = 6  # ramp down, stay in QUICK_STOP_ACTIVE (CiA 402)
# SYNC cycles watched after the stop was applied: far more than any frame stays held.
WATCHED_SYNCS = 40


def synchronous_vendor():
    """Return the vendor layout with every RPDO synchronous (applied at the next SYNC)."""
    return tuple(replace(pdo, transmission_type=1) if pdo.kind == 'rpdo' else pdo
                 for pdo in drive_pdos('vendor'))


class Applied:
    """Every controlword the drive applied and every state it entered, with the time."""

    def __init__(self, drive):
        self._lock = threading.Lock()
        self.events = []  # (monotonic, 'cw' | 'state', value, velocity)
        act, enter = drive._act_on_controlword, drive._enter

        def acted(controlword):
            act(controlword)
            with self._lock:
                self.events.append((time.monotonic(), 'cw', controlword, drive._velocity))

        def entered(state):
            enter(state)
            with self._lock:
                self.events.append((time.monotonic(), 'state', state.name, drive._velocity))
        drive._act_on_controlword, drive._enter = acted, entered

    def since(self, start: float):
        """Return the events from ``start`` on."""
        with self._lock:
            return [event for event in self.events if event[0] >= start]

    def first(self, condition, what: str, since: float = 0.0):
        """Wait for an event ``condition(event)``; return it."""
        def found():
            return next((e for e in self.since(since) if condition(e)), None)
        return wait_until(found, ANSWER, what)


def syncs_pass(axis, count: int, since: int) -> None:
    """Return once ``count`` SYNCs went by on the bus from recording position ``since``."""
    wait_until(lambda: sum(m.arbitration_id == SYNC for m in axis.recorder.messages(since))
               >= count, ANSWER * 2, f'{count} SYNCs on the bus')


def synchronous_axis(rig, period: float, *parameters: str, managed: bool = False):  # noqa: F811
    """Return a rig whose drive has synchronous vendor RPDOs, once the gateway read it.

    ``managed``: the node is the lifecycle node (MANAGED parameters), made active.
    """
    if managed:
        axis = rig(*MANAGED, '-p', f'sync.period:={period}', *parameters,
                   pdos=synchronous_vendor(), program='cbcan_lifecycle_node')
        configure_once_read(axis)
        managed_transition(axis, Transition.TRANSITION_ACTIVATE)
    else:
        axis = rig('-p', f'sync.period:={period}', *parameters, pdos=synchronous_vendor())
    axis.wait_state('SWITCH_ON_DISABLED')
    return axis


def streaming(rig, period: float, *parameters: str, managed: bool = False):  # noqa: F811
    """Return (rig, Applied): the drive streamed VELOCITY on synchronous vendor RPDOs."""
    axis = synchronous_axis(rig, period, *parameters, managed=managed)
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', STAY_IN_QUICK_STOP))
    applied = Applied(axis.drive)
    axis.enable_moving()
    return axis, applied


def summary(events) -> str:
    return ' '.join(f'{kind}={value:#06x}' if kind == 'cw' else f'{value}'
                    for _, kind, value, _ in events[-30:])


PERIODS = [0.004, 0.01]


@pytest.mark.parametrize('period', PERIODS)
@pytest.mark.parametrize('how', ['quick_stop', 'SIGINT', 'deactivate'])
def test_a_quick_stopped_drive_on_synchronous_rpdos_never_runs_again(rig, period, how):  # noqa: F811
    # Deactivated, the managed node keeps the bus open and SYNC going: whatever frame the
    # drive holds for the next SYNC is applied after the stop by SDO.
    axis, applied = streaming(rig, period, '-p', 'drives.command_timeout:=0.0',
                              managed=how == 'deactivate')
    start = time.monotonic()
    before = axis.recorder.mark()
    if how == 'quick_stop':
        stopped = axis.command('quick_stop')
        assert stopped.success, stopped.message
    elif how == 'deactivate':
        managed_transition(axis, Transition.TRANSITION_DEACTIVATE)
    else:
        stop_with(axis, signal.SIGINT)
    stop = applied.first(lambda e: e[1] == 'state' and e[2] == 'QUICK_STOP_ACTIVE',
                         'the drive entering QUICK_STOP_ACTIVE', start)
    if how != 'SIGINT':
        syncs_pass(axis, WATCHED_SYNCS, before)
    axis.stop_streams()
    after = applied.since(stop[0])
    again = [e for e in after if e[1] == 'state' and e[2] == 'OPERATION_ENABLED']
    assert not again, (f'the drive ran again after its quick stop ({how}); applied since: '
                       f'{summary(after)}')
    wait_until(lambda: axis.drive.velocity == 0, ANSWER, 'the drive standing')


@pytest.mark.parametrize('period', PERIODS)
@pytest.mark.parametrize('how', ['halt', 'command_timeout'])
def test_a_halted_drive_on_synchronous_rpdos_stays_halted(rig, period, how):  # noqa: F811
    axis, applied = streaming(rig, period, '-p', 'drives.command_timeout:='
                              + ('0.3' if how == 'command_timeout' else '0.0'))
    start = time.monotonic()
    if how == 'halt':
        halted = axis.command('halt')  # the targets stream on: refused while halted
        assert halted.success, halted.message
    else:
        axis.stop_streams()
    halt = applied.first(lambda e: e[1] == 'cw' and e[2] & HALT,
                         'the drive applying the halt bit', start)
    wait_until(lambda: axis.drive.velocity == 0, ANSWER, 'the drive standing')
    before = axis.recorder.mark()
    syncs_pass(axis, WATCHED_SYNCS, before)
    after = applied.since(halt[0])
    released = [e for e in after if e[1] == 'cw' and not e[2] & HALT]
    assert not released, (f'the drive released the halt ({how}) without a command; applied '
                          f'since: {summary(after)}')
    assert axis.drive.velocity == 0 and axis.drive.drive_state == 'OPERATION_ENABLED'
