"""Boot configuration as a service: every device booted at start and at each of its boot-ups.

For each device of the bus description (or of ``pdo.configure``) a boot (``process.py``) runs
at gateway start, at every boot-up message the device sends, when it is heard again after
being lost, and on request (``boot``). Boots of different devices run in parallel, one at a
time per device; a new boot-up ends the boot running for that device, and no write of the old
boot goes out after it. A device is started (NMT start) only after its boot succeeded, and only
once every ``mandatory`` device has booted; a device whose boot failed is never started.

Each device's state (``WAITING``, ``BOOTING``, ``BOOTED``, ``FAILED``, ``IGNORED``) with its
CiA 302-2 error status letter is kept for callers and listeners (the ROS layer publishes it).
"""

from concurrent.futures import Future
from dataclasses import dataclass, replace
import logging
import math
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from .. import nmt
from ..bus import BusStatus, prompt
from ..program.download import ProgramSettings, Progress
from ..sdo.request_queue import answer, resolved
from ..text import SHUTTING_DOWN
from .plan import BootSettings, DevicePlan
from .process import BootEnded, BootFailed, BootLink, DeviceBoot

LOGGER = logging.getLogger(__name__)

WAITING, BOOTING, BOOTED, FAILED, IGNORED = 'WAITING', 'BOOTING', 'BOOTED', 'FAILED', 'IGNORED'
DEFAULT_CALL_TIMEOUT = 30.0  # s a boot call waits for its boots when it names no timeout
MAX_BOOT_WAIT = 3600.0  # s a boot call may wait (a boot with a program download is long)


@dataclass(frozen=True)
class BootState:
    """One device's boot as callers see it."""

    node_id: int
    name: str
    state: str = WAITING
    error_status: str = ''  # CiA 302-2 letter of the last failure, '' without one
    message: str = ''
    writes: int = 0         # objects written in its last boot
    boots: int = 0          # boots completed since the gateway started
    stamp: float = 0.0      # time.time() of the last change


@dataclass(frozen=True)
class BootAnswer:
    """The answer to a boot request."""

    success: bool
    message: str
    states: Tuple[BootState, ...] = ()


class _Device:
    def __init__(self, plan: DevicePlan, mutex):
        self.plan = plan
        self.state = BootState(plan.node_id, plan.name, WAITING if plan.boot else IGNORED,
                               message='' if plan.boot else 'boot: false in the bus '
                               'description: left alone', stamp=time.time())
        self.wanted = 0            # boots asked for; each ends the one running
        self.done = 0              # the last boot that ended (with a verdict or not)
        self.booted_itself = False  # the boot wanted was started by its own boot-up
        self.running = False       # a boot is asked for or runs (its thread is not idle)
        # The device's boot thread, started once and idle between boots: a boot-up (handled
        # on the bus receive thread) only wakes it. Starting a thread there waited for the
        # new thread to run, holding up every frame behind the boot-up.
        self.thread: Optional[threading.Thread] = None
        self.wake = threading.Condition(mutex)  # the service's lock; told of a boot wanted
        self.ready = False         # booted, waiting to be started
        self.awaiting_boot_up = False
        self.boot_ups = 0          # every boot-up heard (awaited, and a download's resets)
        self.heartbeats = 0
        self.heard = False
        self.lost = False
        self.interrupted = False   # its boot was ended by the bus going down
        self.held = False          # a boot asked for while it is being programmed
        self.waiters: List[Tuple[int, Future]] = []


class BootService:
    """The boots of the devices of ``settings``, on the gateway's network.

    ``sdo_batch(accesses, timeout, stop)`` is the gateway's (``stop()``: why the rest of a
    batch must not be sent, or None); ``nmt_command(node_id, command)`` its NMT command;
    ``pdo`` its PDO service (mappings read again after a boot); ``monitor`` its heartbeat
    monitor (a device lost and heard again boots again); ``drive_enabled(node_id)`` whether
    a drive is running (a boot call is refused then).
    """

    def __init__(self, network, settings: BootSettings, sdo_batch, nmt_command, pdo, monitor,
                 deadlines, sdo_timeout: float,
                 drive_enabled: Callable[[int], bool] = lambda node_id: False,
                 sdo_stream=None, program: ProgramSettings = ProgramSettings()):
        self._network = network
        self._settings = settings
        self._sdo_batch = sdo_batch
        self._nmt_command = nmt_command
        self._pdo = pdo
        self._monitor = monitor
        self._deadlines = deadlines
        self._sdo_timeout = sdo_timeout
        self._drive_enabled = drive_enabled
        self._sdo_stream = sdo_stream
        self._program = program
        mutex = threading.RLock()
        self._devices: Dict[int, _Device] = {plan.node_id: _Device(plan, mutex)
                                             for plan in settings.plans}
        self._lock = threading.Condition(mutex)
        self._closing = False
        self._bus_down = ''
        self._listeners: List[Callable[[], None]] = []
        # Why a device must not be booted now (a program download is writing it), or None;
        # why its program is not whole (a download failed), or ''.
        self._programming: Callable[[int], Optional[str]] = lambda node_id: None
        self._cleared: Callable[[int], str] = lambda node_id: ''
        self._downloads: Dict[int, Progress] = {}  # the boots' own program downloads

    def hold_while(self, programming: Callable[[int], Optional[str]],
                   cleared: Callable[[int], str]) -> None:
        """Hold every boot of a device for which ``programming(node_id)`` says why not.

        Its boot-ups then come from the download (the bootloader, the new program): one boot
        runs once the download ended (``program_changed``), which configures what it left.
        A device for which ``cleared(node_id)`` says why its program is not whole (that
        download failed) is neither configured nor started (error I) until a download mends
        it.
        """
        self._programming = programming
        self._cleared = cleared

    def program_changed(self) -> None:
        """Boot each device held for its download, now that nothing programs it any more."""
        with self._lock:
            for device in self._devices.values():
                if device.held and not self._closing and not self._programming(
                        device.plan.node_id):
                    device.held = False
                    self._want(device, True)

    def booting(self, node_id: int) -> Optional[str]:
        """Return why ``node_id`` must not be programmed now (its boot runs), or None."""
        with self._lock:
            device = self._devices.get(node_id)
            running = device is not None and (device.running or device.state.state == BOOTING)
        return (f'node {node_id} is being booted (its boot configuration runs, '
                f'~/boot_states): download once it has ended') if running else None

    def programming(self) -> Dict[int, Progress]:
        """Return the devices a boot is programming now (software_file), with its progress."""
        with self._lock:
            return dict(self._downloads)

    def program_conflict(self, node_id: int, program: int,
                         expected_software_id: int) -> Optional[str]:
        """Return why a download of ``program`` to ``node_id`` would not last, or None.

        Its boot checks 0x1F56:1 against the bus description's ``software_version``: any
        other program 1 would be downloaded over at the next boot (``software_file``,
        ``program_download.at_boot``) or fail it (error H), leaving the device unstarted.
        """
        device = self._devices.get(node_id)
        wanted = device.plan.software_version if device is not None else None
        if wanted is None or not device.plan.boot or program != 1 \
                or expected_software_id == wanted:
            return None
        given = (f'expected_software_id 0x{expected_software_id:08X}' if expected_software_id
                 else 'no expected_software_id')
        then = ('download its software_file over it' if device.plan.software_file
                and self._program.at_boot else 'fail (CiA 302-2 error H) and leave it '
                                                'unstarted')
        return (f"node {node_id}'s bus description asks for software_version 0x{wanted:08X} "
                f'and the goal gives {given}: its next boot would {then}. Give '
                f'expected_software_id 0x{wanted:08X} to download that program, or change '
                f'software_version (and software_file) in the bus description first')

    @property
    def node_ids(self) -> List[int]:
        """Return the devices booted (IGNORED ones included)."""
        return sorted(self._devices)

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` (from a boot or bus thread, no lock held) after every change."""
        self._listeners.append(listener)

    def states(self) -> List[BootState]:
        """Return every device's boot state, by node id."""
        with self._lock:
            return [self._devices[node_id].state for node_id in sorted(self._devices)]

    def refusal(self, node_id: int) -> Optional[str]:
        """Return why ``node_id`` must not be run now (its boot did not succeed), or None."""
        device = self._devices.get(node_id)
        if device is None or not device.plan.boot:
            return None
        state = device.state
        if state.state == BOOTED:
            return None
        if state.state == FAILED:
            return (f'its boot failed (CiA 302-2 error {state.error_status}: {state.message}); '
                    f'it was not started')
        return f'its boot has not succeeded ({state.state}: {state.message or "not yet run"})'

    def start(self) -> None:
        """Listen to the devices' heartbeats and boot every device once."""
        for node_id in self._devices:
            self._network.subscribe(nmt.HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        if self._devices:
            self._monitor.add_listener(self._on_node_states)
        with self._lock:
            for device in self._devices.values():
                if device.plan.boot:
                    self._want(device, False)

    def stop(self) -> None:
        """End every boot: nothing more is written; callers waiting are answered."""
        with self._lock:
            self._closing = True
            self._lock.notify_all()
            for device in self._devices.values():
                device.wake.notify()
            waiters = [waiter for device in self._devices.values() for waiter in device.waiters]
            for device in self._devices.values():
                device.waiters = []
        for node_id in self._devices:
            self._network.unsubscribe(nmt.HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        for _, future in waiters:
            answer(future, BootAnswer(False, f'{SHUTTING_DOWN}: the boot ended'))

    def on_bus_change(self, status: BusStatus) -> None:
        """End every boot while the bus is down; boot every device heard again after it."""
        with self._lock:
            self._bus_down = '' if status.up else f'the CAN bus is down: {status.reason}'
            if status.up:
                # A boot the bus ended is run again now: a device that sends no heartbeat
                # would never be heard again to be booted. Heard, it boots once, not twice.
                for device in self._devices.values():
                    if device.interrupted:
                        device.interrupted = device.lost = False
                        self._want(device, False)
                return
            for device in self._devices.values():
                if device.heard:
                    device.lost = True
            self._lock.notify_all()

    def boot(self, node_id: int, timeout: float = 0.0) -> 'Future[BootAnswer]':
        """Boot ``node_id`` again (0: every device); resolves when its boot ended.

        Refused at once for a device the bus description does not name, one it leaves alone
        (``boot: false``) and a drive that is running (disable it first). A boot still
        running after ``timeout`` s (0: 30 s) is answered as such; it goes on.
        """
        if not (math.isfinite(timeout) and 0 <= timeout <= MAX_BOOT_WAIT):
            # An endless deadline would stop the gateway's one deadline thread for every call.
            return resolved(BootAnswer(False, f'timeout {timeout}: allowed 0 (30 s) up to '
                                              f'{MAX_BOOT_WAIT:g} s'))
        if node_id and node_id not in self._devices:
            named = ', '.join(map(str, self._devices)) or 'none'
            return resolved(BootAnswer(False, f'node_id {node_id} is not booted by the '
                                              f'gateway (its devices: {named})'))
        chosen = [node_id] if node_id else [n for n, d in self._devices.items() if d.plan.boot]
        if not chosen:
            return resolved(BootAnswer(False, 'the gateway boots no device: give a bus '
                                              'description (parameter bus_config)'))
        for chosen_id in chosen:
            device = self._devices[chosen_id]
            if not device.plan.boot:
                return resolved(BootAnswer(False, f'node {device.plan.label} has boot: false '
                                                  f'in the bus description: left alone'))
            if self._drive_enabled(chosen_id):
                return resolved(BootAnswer(False, f'drive {device.plan.label} is '
                                                  f'OPERATION_ENABLED: disable it first, a '
                                                  f'boot resets and stops it'))
            programming = self._programming(chosen_id)
            if programming:
                return resolved(BootAnswer(False, f'{programming}: it is booted once the '
                                                  f'download has ended'))
        futures = []
        with self._lock:
            if self._closing:
                return resolved(BootAnswer(False, f'{SHUTTING_DOWN}; nothing was sent'))
            for chosen_id in chosen:
                device = self._devices[chosen_id]
                self._want(device, False)
                future: Future = Future()
                device.waiters.append((device.wanted, future))
                futures.append(future)
        return self._collect(chosen, futures, timeout or DEFAULT_CALL_TIMEOUT)

    def _collect(self, node_ids: Sequence[int], futures: List[Future],
                 timeout: float) -> 'Future[BootAnswer]':
        done: Future = Future()
        remaining = [len(futures)]
        lock = threading.Lock()

        def finish() -> None:
            states = [state for state in self.states() if state.node_id in node_ids]
            failed = [f'{s.node_id}: {s.error_status or s.state} {s.message}'.strip()
                      for s in states if s.state != BOOTED]
            ended = [f'{node_id}: {future.result().message}'  # named, as the failures are
                     for node_id, future in zip(node_ids, futures, strict=True)
                     if future.done() and not future.result().success]
            if ended:
                failed = ended
            answer(done, BootAnswer(not failed, '; '.join(failed) or
                                    f'{len(states)} device(s) booted', tuple(states)))

        def one_done(_future) -> None:
            with lock:
                remaining[0] -= 1
                last = remaining[0] == 0
            if last:
                self._deadlines.cancel(watch)
                finish()

        def expire() -> None:
            states = [state for state in self.states() if state.node_id in node_ids]
            busy = [str(s.node_id) for s in states if s.state == BOOTING]
            answer(done, BootAnswer(False, f'still booting after {timeout:g} s: nodes '
                                           f'{", ".join(busy) or "-"}; the boot goes on, '
                                           f'~/boot_states shows its end', tuple(states)))

        watch = self._deadlines.watch(time.monotonic() + timeout, expire)
        for future in futures:
            future.add_done_callback(one_done)
        return done

    def _want(self, device: _Device, booted_itself: bool) -> None:
        """Ask for a new boot of ``device`` (lock held): it ends the one running.

        Held while the device is being programmed: a boot-up then is the download's.
        """
        if self._programming(device.plan.node_id):
            device.held = True
            return
        device.wanted += 1
        device.booted_itself = booted_itself
        device.ready = False
        self._lock.notify_all()
        device.running = True
        if device.thread is None:
            device.thread = threading.Thread(target=self._run, args=(device,), daemon=True,
                                             name=f'boot-{device.plan.node_id}')
            device.thread.start()
        else:
            device.wake.notify()

    def _run(self, device: _Device) -> None:
        while True:
            with self._lock:
                while not self._closing and device.done >= device.wanted:
                    device.running = False
                    device.wake.wait()
                if self._closing:
                    device.running = False
                    return
                generation, booted_itself = device.wanted, device.booted_itself
            self._set(device, generation, state=BOOTING, error_status='',
                      message='booted again by its boot-up' if booted_itself else 'booting')
            self._boot_once(device, generation, booted_itself)

    def _boot_once(self, device: _Device, generation: int, booted_itself: bool) -> None:
        plan = device.plan
        run = DeviceBoot(plan, self._link(device, generation), self._sdo_timeout,
                         self._settings.boot_timeout, booted_itself, self._program)
        try:
            outcome = run.run()
        except BootEnded as ended:
            with self._lock:
                current = device.wanted == generation
                device.done = max(device.done, generation)
                if current and not self._closing:  # the bus: booted again when it is back
                    if self._bus_down:
                        device.interrupted = True
                    else:  # back already
                        self._want(device, False)
            if current:  # shutdown or the bus: no new boot follows at once
                self._set(device, generation, state=WAITING,
                          message=f'boot ended: {ended}; booted again when the bus is back')
                self._answer_waiters(device, generation)
            return
        except Exception as error:  # noqa: BLE001 - a defect must not leave BOOTING for ever
            if isinstance(error, BootFailed):
                failure = error
            else:
                LOGGER.exception('node %s: the boot stopped on an error', plan.label)
                failure = BootFailed('J', f'the boot stopped on an error of the gateway: '
                                          f'{error!r}')
            LOGGER.error('node %s: boot failed (CiA 302-2 error %s): %s; not started',
                         plan.label, failure.letter, failure.message)
            self._set(device, generation, done=True, state=FAILED,
                      error_status=failure.letter, message=failure.message)
            if plan.pdos:  # served as the device has them: it is not started by the gateway
                self._pdo.read_again(plan.node_id)
            self._start_ready()  # the devices a failed mandatory one holds say so
            return
        with self._lock:
            if device.wanted == generation:
                device.ready = True
                # Done: its start may be sent by another device's thread (_start_ready),
                # and this thread must not take the boot for one still to run.
                device.done = generation
        self._set(device, generation, writes=outcome.writes, message=outcome.message)
        self._start_ready()

    def _start_ready(self) -> None:
        """Start every device booted and waiting, once every mandatory device has booted."""
        with self._lock:
            # A mandatory device left alone (boot: false) is not booted, so not waited for:
            # nothing the gateway does could end that wait.
            holding = [device for device in self._devices.values()
                       if device.plan.mandatory and device.plan.boot
                       and device.state.state != BOOTED and not device.ready]
            # The generation of each boot taken, with the lock: a boot-up after this moment
            # begins a newer boot, which this start must not be taken for.
            ready = [(device, device.wanted) for device in self._devices.values()
                     if device.ready]
            for device, _ in ready:
                device.ready = False
        for device, generation in ready:
            others = [d for d in holding if d is not device]
            if others:
                self._hold(device, generation, others)
                continue
            self._start(device, generation)

    def _hold(self, device: _Device, generation: int, mandatory: List[_Device]) -> None:
        failed = [d for d in mandatory if d.state.state == FAILED]
        if failed:
            why = '; '.join(f'{d.plan.label} failed its boot ({d.state.error_status}: '
                            f'{d.state.message})' for d in failed)
            text = f'configured and verified, not started: mandatory device {why}'
        else:
            text = ('configured and verified, waiting for mandatory device(s) '
                    + ', '.join(d.plan.label for d in mandatory))
        with self._lock:
            if device.wanted == generation:
                device.ready = True
        self._set(device, generation, done=True, state=WAITING, message=text)

    def _start(self, device: _Device, generation: int) -> None:
        plan = device.plan
        message = device.state.message
        if not (plan.start and self._settings.start_nodes):
            why = 'start: false' if not plan.start else 'master start_nodes: false'
            self._set(device, generation, done=True, state=BOOTED,
                      message=f'{message}; not started ({why})'.lstrip('; '))
            return
        with self._lock:
            problem = self._ended(device, generation)
        if not problem:
            result = self._nmt_command(plan.node_id, nmt.START)
            problem = '' if result.success else f'NMT start not sent: {result.message}'
        if problem:
            self._set(device, generation, done=True, state=WAITING,
                      message=f'configured, not started: {problem}')
            return
        LOGGER.info('node %s booted: %s; started', plan.label, message or 'nothing written')
        self._set(device, generation, done=True, state=BOOTED,
                  message=f'{message}; started'.lstrip('; '))

    def _set(self, device: _Device, generation: int, done: bool = False, **changes) -> None:
        """Change the device's state, unless a newer boot was asked for meanwhile."""
        with self._lock:
            if device.wanted != generation:
                return
            boots = device.state.boots + (1 if done and changes.get('state') in (
                BOOTED, FAILED) else 0)
            if done:
                device.done = max(device.done, generation)
            device.state = replace(device.state, boots=boots, stamp=time.time(), **changes)
        if done:
            self._answer_waiters(device, generation)
        for listener in self._listeners:
            listener()

    def _answer_waiters(self, device: _Device, generation: int) -> None:
        with self._lock:
            answered = [future for wanted, future in device.waiters if wanted <= generation]
            device.waiters = [(wanted, future) for wanted, future in device.waiters
                              if wanted > generation]
        for future in answered:
            answer(future, BootAnswer(True, ''))

    def _ended(self, device: _Device, generation: int) -> str:
        """Return why the boot ``generation`` of ``device`` must end (lock held), or ''."""
        if self._closing:
            return SHUTTING_DOWN
        if self._bus_down:
            return self._bus_down
        if device.wanted != generation:
            return 'the device booted again (or a new boot was asked for)'
        return ''

    def _link(self, device: _Device, generation: int) -> BootLink:
        node_id = device.plan.node_id
        # Heartbeats of this boot: those heard since it began, or since the boot-up of a
        # reset it sent. Error control is started when the boot starts listening, as a
        # consumer does, not after the writes: one heard meanwhile counts.
        with self._lock:
            heard_before = [device.heartbeats]

        def ended() -> str:
            with self._lock:
                return self._ended(device, generation)

        def sdo(accesses, timeout):
            def stop(results) -> Optional[str]:
                # Asked before each access: the ones before the last were looked at already
                # (a batch stops at the first failure; each access after it fails too).
                if results and not results[-1].success:
                    return 'an earlier access of the boot failed'
                return ended() or None
            return self._sdo_batch(accesses, timeout, stop).result()

        def nmt_send(command: int) -> str:
            result = self._nmt_command(node_id, command)
            return '' if result.success else result.message

        def await_boot_up(send: Callable[[], str], timeout: float) -> bool:
            with self._lock:
                device.awaiting_boot_up = True
                seen = device.boot_ups
            try:
                if send():
                    return False
                deadline = time.monotonic() + timeout
                with self._lock:
                    while device.boot_ups == seen and not self._ended(device, generation):
                        left = deadline - time.monotonic()
                        if left <= 0:
                            return False
                        self._lock.wait(left)
                    heard_before[0] = device.heartbeats
                    return device.boot_ups != seen
            finally:
                with self._lock:
                    device.awaiting_boot_up = False

        def await_heartbeat(timeout: float) -> bool:
            deadline = time.monotonic() + timeout
            with self._lock:
                while (device.heartbeats == heard_before[0]
                       and not self._ended(device, generation)):
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    self._lock.wait(left)
                return device.heartbeats != heard_before[0]

        def read_pdos() -> str:
            return self._pdo.read_again(node_id).result()

        def stream(access, answer_within, written):
            return self._sdo_stream(access, answer_within, written).result()

        def boot_ups() -> int:
            with self._lock:
                return device.boot_ups

        def programming(progress: Optional[Progress]) -> None:
            with self._lock:
                if progress is None:
                    shown_changed = self._downloads.pop(node_id, None) is not None
                else:
                    shown_changed = node_id not in self._downloads
                    self._downloads[node_id] = progress
            if shown_changed:  # shown as being programmed, or no more
                for listener in self._listeners:
                    listener()

        return BootLink(sdo, nmt_send, ended, await_boot_up, await_heartbeat, read_pdos,
                        stream, programming, boot_ups, lambda: self._cleared(node_id))

    @prompt
    def _on_heartbeat(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        if not data:
            return
        with self._lock:
            device = self._devices[can_id - nmt.HEARTBEAT_COB_BASE]
            if not device.plan.boot or self._closing:
                return
            again = device.lost
            device.heard, device.lost = True, False
            if data[0] == nmt.BOOT_UP:
                device.boot_ups += 1
                if device.awaiting_boot_up:
                    self._lock.notify_all()
                else:
                    self._want(device, True)
                return
            device.heartbeats += 1
            self._lock.notify_all()
            if again:
                self._want(device, False)

    def _on_node_states(self) -> None:
        lost = [node_id for node_id, device in self._devices.items()
                if device.heard and not self._monitor.status(node_id).detected]
        if lost:
            with self._lock:
                for node_id in lost:
                    device = self._devices[node_id]
                    # Silent during its own boot is no loss: a device whose factory 0x1017
                    # is 0 sends nothing until the boot writes it, and its first heartbeat
                    # would start the boot again (and the reset silence it again).
                    if not device.running:
                        device.lost = True
