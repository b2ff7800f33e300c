"""A fake USB-CAN adapter speaking slcan (Lawicel ASCII) on a pseudo-terminal.

python-can's real ``slcan`` driver opens it through a stable symlink, as it would open
``/dev/serial/by-id/...`` on a robot::

    adapter = FakeSlcanAdapter(tmp_path / 'usb-can', channel='bench')
    bus = can.Bus(interface='slcan', channel=str(tmp_path / 'usb-can'), bitrate=500000,
                  sleep_after_open=0)

The CAN side of the adapter is a python-can ``virtual`` bus on ``channel``, where simulated
devices live. Once the driver has opened the CAN channel (``O``, or ``L`` for listen-only),
frames the driver transmits (``t``/``T``/``r``/``R`` lines) go onto the virtual bus and frames
from the virtual bus reach the driver as ``t``/``T``/``r``/``R`` lines without timestamps; while
the channel is closed, transmits are refused with BELL and bus frames are dropped, as on a real
adapter. Replies follow Lawicel: CR for a done command, BELL (byte 7) for a refused or unknown
one, ``z``/``Z`` CR after a transmit, ``V1013``, ``NFAKE`` and ``F00`` for the queries.
(python-can 4.6.1 never waits for these replies and ignores BELL.)

``unplug()`` removes the symlink and closes the pty master: the driver's slave fd is hung up,
so its next read or write fails (python-can raises ``can.CanOperationError``) and opening the
path fails with ``can.CanInitializationError`` until ``plug()`` creates a new pty and points
the symlink at it. The adapter holds a slave fd of its own while plugged so that its reads on
the master do not fail while no driver has the port open; closing the master hangs up every
slave fd regardless, so this does not hide the unplug from the driver.
"""

import os
import select
import threading
import tty
from typing import List, Optional

import can

WRITE_TIMEOUT = 1.0  # seconds a line to the driver may wait for room before it is dropped
OK = b'\r'
BELL = b'\a'


def encode(msg: can.Message) -> Optional[bytes]:
    """Return the slcan line (with CR) for a classic CAN frame, or None if slcan can't carry it."""
    if msg.is_error_frame or msg.is_fd:
        return None
    if msg.is_remote_frame:
        prefix = 'R' if msg.is_extended_id else 'r'
        data = ''
    else:
        prefix = 'T' if msg.is_extended_id else 't'
        data = bytes(msg.data[:msg.dlc]).hex().upper()
    width = 8 if msg.is_extended_id else 3
    return f'{prefix}{msg.arbitration_id:0{width}X}{msg.dlc:d}{data}\r'.encode('ascii')


def decode(line: str) -> can.Message:
    """Return the frame of a ``t``/``T``/``r``/``R`` transmit command; ValueError if malformed."""
    extended = line[0] in 'TR'
    remote = line[0] in 'rR'
    width = 8 if extended else 3
    can_id = int(line[1:1 + width], 16)
    dlc = int(line[1 + width], 16)
    if dlc > 8 or can_id >= (1 << (29 if extended else 11)):
        raise ValueError(f'bad frame {line!r}')
    data = b'' if remote else bytes.fromhex(line[2 + width:2 + width + 2 * dlc])
    if len(data) != (0 if remote else dlc):
        raise ValueError(f'bad frame {line!r}')
    return can.Message(arbitration_id=can_id, is_extended_id=extended, is_remote_frame=remote,
                       dlc=dlc, data=data)


class _Plug:
    """One plugged-in period: a pty, its command reader thread and the CAN channel state."""

    def __init__(self, adapter: 'FakeSlcanAdapter'):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.tty_path = os.ttyname(self.slave)
        self.wake_read, self.wake_write = os.pipe()
        self.stopped = False
        self.is_open = False
        self.listen_only = False
        self.write_lock = threading.Lock()
        self.reader = threading.Thread(target=adapter._serve, args=(self,), daemon=True,
                                       name=f'fake-slcan {self.tty_path}')

    def write(self, data: bytes) -> bool:
        """Write ``data`` to the driver; False if unplugged or no room within WRITE_TIMEOUT."""
        with self.write_lock:
            rest = memoryview(data)
            waited = 0.0
            while rest and not self.stopped:
                try:
                    rest = rest[os.write(self.master, rest):]
                    continue
                except BlockingIOError:
                    pass
                except OSError:
                    return False
                if waited >= WRITE_TIMEOUT:
                    return False
                select.select([], [self.master], [], 0.05)
                waited += 0.05
            return not rest

    def stop(self) -> None:
        """End the reader thread and close every fd: the driver's slave sees a hang-up."""
        self.stopped = True
        os.write(self.wake_write, b'x')
        if self.reader.is_alive() and self.reader is not threading.current_thread():
            self.reader.join()
        with self.write_lock:
            for fd in (self.master, self.slave, self.wake_read, self.wake_write):
                os.close(fd)


class FakeSlcanAdapter:
    """A USB-CAN adapter on a pty behind ``link_path``, bridging to virtual bus ``channel``.

    It starts plugged in (unless ``plugged=False``). Counters: ``frames_to_bus`` (transmits from
    the driver put on the virtual bus), ``frames_to_driver`` (bus frames written to the driver),
    ``frames_dropped`` (bus frames not delivered: channel closed, unplugged, or no room),
    ``open_count`` (times the driver opened the CAN channel, over all plugs), ``plug_count``,
    ``commands`` (every line the driver sent, without CR).
    """

    def __init__(self, link_path, channel: str, plugged: bool = True):
        self.link_path = os.fspath(link_path)
        self.channel = channel
        self.frames_to_bus = 0
        self.frames_to_driver = 0
        self.frames_dropped = 0
        self.open_count = 0
        self.plug_count = 0
        self._commands: List[str] = []
        self._lock = threading.Lock()
        self._plug: Optional[_Plug] = None
        self._closing = False
        self._bus = can.Bus(interface='virtual', channel=channel)
        self._forwarder = threading.Thread(target=self._forward, daemon=True,
                                           name=f'fake-slcan bus {channel}')
        self._forwarder.start()
        if plugged:
            self.plug()

    @property
    def plugged(self) -> bool:
        """Return whether the adapter is plugged in."""
        return self._plug is not None

    @property
    def is_open(self) -> bool:
        """Return whether the driver has opened the CAN channel of the current plug."""
        plug = self._plug
        return plug is not None and plug.is_open

    @property
    def tty_path(self) -> Optional[str]:
        """Return the pty slave the link points at now, or None while unplugged."""
        plug = self._plug
        return plug.tty_path if plug is not None else None

    @property
    def commands(self) -> List[str]:
        """Return a copy of the lines the driver has sent, oldest first."""
        with self._lock:
            return list(self._commands)

    def plug(self) -> None:
        """Plug in: a new pty, its command reader, and ``link_path`` pointing at it."""
        with self._lock:
            if self._closing:
                raise RuntimeError('adapter is closed')
            if self._plug is not None:
                return
            plug = _Plug(self)
            self._plug = plug
            self.plug_count += 1
        plug.reader.start()
        temporary = f'{self.link_path}.plugging-{os.getpid()}'
        os.symlink(plug.tty_path, temporary)
        os.replace(temporary, self.link_path)

    def unplug(self) -> None:
        """Unplug: remove ``link_path`` and close the pty, hanging up the driver's port."""
        with self._lock:
            plug, self._plug = self._plug, None
        if plug is None:
            return
        try:
            os.unlink(self.link_path)
        except FileNotFoundError:
            pass
        plug.stop()

    def close(self) -> None:
        """Unplug and leave the virtual bus for good."""
        with self._lock:
            self._closing = True
        self.unplug()
        self._forwarder.join()
        self._bus.shutdown()

    def __enter__(self) -> 'FakeSlcanAdapter':
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _serve(self, plug: _Plug) -> None:
        """Answer the driver's commands until ``plug`` is pulled."""
        buffer = bytearray()
        while not plug.stopped:
            ready, _, _ = select.select([plug.master, plug.wake_read], [], [])
            if plug.wake_read in ready or plug.stopped:
                return
            try:
                data = os.read(plug.master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                return
            buffer.extend(data.replace(b'\n', b''))
            while OK in buffer:
                line, _, rest = bytes(buffer).partition(OK)
                buffer[:] = rest
                plug.write(self._answer(plug, line.decode('ascii', 'replace')))

    def _answer(self, plug: _Plug, line: str) -> bytes:
        """Carry out one command line and return the reply."""
        with self._lock:
            self._commands.append(line)
        command = line[:1]
        if command == 'C':
            plug.is_open = False
            return OK
        if command in ('O', 'L'):
            if plug.is_open:
                return BELL
            plug.listen_only = command == 'L'
            plug.is_open = True
            with self._lock:
                self.open_count += 1
            return OK
        if command in ('S', 's', 'Y', 'Z'):
            return BELL if plug.is_open and command != 'Z' else OK
        if command == 'V':
            return b'V1013\r'
        if command == 'N':
            return b'NFAKE\r'
        if command == 'F':
            return b'F00\r' if plug.is_open else BELL
        if command and command in 'tTrR':
            if not plug.is_open or plug.listen_only:
                return BELL
            try:
                msg = decode(line)
            except (ValueError, IndexError):
                return BELL
            self._bus.send(msg)
            with self._lock:
                self.frames_to_bus += 1
            return b'Z\r' if command in 'TR' else b'z\r'
        return BELL

    def _forward(self) -> None:
        """Write frames from the virtual bus to the driver while its channel is open."""
        while not self._closing:
            msg = self._bus.recv(0.02)
            if msg is None:
                continue
            plug = self._plug
            line = encode(msg)
            delivered = (plug is not None and plug.is_open and line is not None
                         and plug.write(line))
            with self._lock:
                if delivered:
                    self.frames_to_driver += 1
                else:
                    self.frames_dropped += 1
