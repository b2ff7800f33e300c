"""canopen 2.4.1's SDO client and transfer streams, with what a gateway needs of them.

canopen's own classes and transfer streams are used; where they fall short for a gateway
that must give every request exactly one right answer, they are extended here and nowhere
else. Each gap is listed in docs/library_gaps.md.

The SDO client (:class:`StrictSdoClient`, one transfer at a time, with the checks CiA 301
asks of a client):

1. Responses are matched to their request: command specifier, index and subindex, toggle
   bit, block sequence answers. canopen checks the multiplexer of upload and block
   responses only, so a download acknowledgement for another object, or a late one, was
   taken as success. Frames for another object are ignored; wrong toggles or command
   specifiers end the transfer with the right abort code, sent on the bus.
2. No frame that arrived before a request was sent counts for it (canopen kept a late
   answer in its queue when it arrived between a timeout and the next request). A
   response's arrival is the moment the gateway's receive thread took it from the driver,
   on the host's monotonic clock (``bus.py`` stamps every frame so and does nothing else on
   that thread, so a slow handler or a burst does not delay the stamp), never the adapter's
   timestamp: adapters' clocks are offset from the host's, by seconds on some, and drift.
3. The caller's deadline bounds the whole transfer, not each frame.
4. The first abort wins: once the device aborted (or the client did), nothing more is sent
   and the answer carries that first code (canopen sends another request after a device's
   abort in a segmented download and reports the device's answer to that one instead). A
   device may abort in the middle of a block download, while the client sends the block
   without waiting: canopen sends the rest of the block, which the device answers with
   0x05040001 each, and reports that. Here a device's abort counts from the transfer's first
   request on (not only after the latest one), and no segment of a block goes out after it.
5. Frames shorter than the 8 bytes CiA 301 prescribes for SDO are ignored (canopen let
   ``struct.error`` escape for them), and aborts name the transfer's index and subindex.
   An abort "unknown command" (0x05040001) of 0000:00 is not taken as the answer to an
   expedited or segmented initiation: every SDO server knows those; it answers a stray frame,
   such as the rest of a block that reached a device restarted meanwhile.
6. A transfer can be cancelled from another thread (bus down, shutdown); it ends at once,
   and so does the rest of the work it is part of (a batch: ``cancels``).
   A long one (a program image) may be bounded by each answer instead (``answer_within``:
   every answer due that long after the request it answers), so that only a device that
   stops answering ends it.

The transfer streams:

7. canopen's segmented download stream is not closed once: after a failed transfer, garbage
   collection closes it again and it sends its end frame in the middle of a later transfer.
   :class:`DownloadStream` closes once; a stream whose initiation failed closes silently,
   and :func:`close_without_frames` ends any stream after a failure without its frames.
8. A segment may carry no data and still announce more: only canopen's private ``_done``
   tells the upload's end (:func:`upload_finished`).
"""

import io
import queue
import struct
import threading
import time
from typing import Callable, Optional, Union

from canopen.sdo.client import SdoClient, WritableStream
from canopen.sdo.exceptions import SdoAbortedError

from ..bus import BusDown, prompt
from ..sdo import abort_codes

# Client command specifiers (CiA 301), top three bits of the first byte of a request.
_CCS_DOWNLOAD_SEGMENT = 0
_CCS_DOWNLOAD = 1
_CCS_UPLOAD = 2
_CCS_UPLOAD_SEGMENT = 3
_CCS_BLOCK_UPLOAD = 5
_CCS_BLOCK_DOWNLOAD = 6

_ABORT = 0x80
_TOGGLE = 0x10
_MUX = struct.Struct('<HB')

IGNORE = 'ignore'
Verdict = Union[None, str, int]  # None: the answer; IGNORE: not ours; int: abort with code


class TransferAborted(SdoAbortedError):
    """The transfer ended with an abort code, the device's or the gateway's."""

    def __init__(self, code: int, detail: str = ''):
        super().__init__(code)
        self.detail = detail


class TransferCancelled(Exception):
    """The transfer was ended from outside (bus down, shutdown); the message says why."""


class _Cancel:
    """Marker put into the response queue to wake a waiting transfer."""


class StrictSdoClient(SdoClient):
    """An ``SdoClient`` for one transfer at a time, run through :meth:`transfer`."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od):
        super().__init__(rx_cobid, tx_cobid, od)
        # A queue only while a transfer runs. queue.SimpleQueue (C): a queue.Queue costs a
        # lock and three conditions to make, and Python code on each put and get, for every
        # transfer, on the receive thread and the transfer's thread both.
        self.responses: Optional[queue.SimpleQueue] = None
        # The devices' aborts of this transfer as they arrived, (arrival, code): a block
        # download looks for one before each segment without taking frames from the queue.
        self._device_aborts: list = []
        # Reentrant: garbage collection may finalize a stream inside a locked section.
        self._lock = threading.RLock()
        self._mux = (0, 0)
        self._kind: Optional[int] = None  # the initiating ccs; None before the initiation
        self._deadline = 0.0
        self._answer_within: Optional[float] = None  # s after each request; None: _deadline
        self._sent_at = 0.0
        self._began = 0.0  # when the transfer's first request went out
        self._sent_any = False
        self.initiated = False  # the device accepted the initiation of this transfer
        self._aborted: Optional[TransferAborted] = None
        self._cancelled: Optional[TransferCancelled] = None
        self._abort_on_cancel: Optional[int] = None
        self.cancels = 0  # calls of cancel() so far, with the reason of the latest
        self._cancel_reason = ''
        self.ignored_frames = 0  # frames of this transfer that answered nothing we asked

    def transfer(self, index: int, subindex: int, deadline: float, run: Callable[[], object],
                 answer_within: Optional[float], cancels: int):
        """Run ``run()`` (canopen stream calls) as one transfer of ``index:subindex``.

        ``deadline`` bounds the whole transfer; with ``answer_within`` each answer is due
        that long after the latest request instead, and ``deadline`` is not used.
        ``cancels``: :attr:`cancels` when the work this transfer is part of began; a cancel
        since then (between the transfers of a batch) ends it before anything is sent.

        It raises only :class:`TransferAborted` (the first abort of the transfer, whatever
        canopen raised after it), :class:`TransferCancelled` or ``BusDown``. Anything else
        canopen raises ends the transfer with a general-error abort on the bus.
        """
        with self._lock:
            if cancels != self.cancels:
                raise TransferCancelled(f'{self._cancel_reason}; not sent')
            self._mux = (index, subindex)
            self._kind = None
            self._deadline = deadline
            self._answer_within = answer_within
            self._sent_any = False
            self.initiated = False
            self.ignored_frames = 0
            self._aborted = None
            self._cancelled = None
            self._abort_on_cancel = None
            self._device_aborts = []
            self.responses = queue.SimpleQueue()
        try:
            return run()
        except BusDown:
            raise
        except Exception as error:
            with self._lock:
                first = self._cancelled or self._aborted
            if first is error:
                raise
            if first is None:
                first = self.fail(abort_codes.GENERAL_ERROR,
                                  f'protocol error: {type(error).__name__}: {error}',
                                  on_bus=self._sent_any)
            raise first from error
        finally:
            # Between transfers nothing is waited for: frames are dropped, not kept.
            self.responses = None

    def fail(self, code: int, detail: str, on_bus: bool = True) -> Exception:
        """End the transfer with ``code``, sent on the bus if ``on_bus``.

        Returns the exception that ends the transfer: the first abort or cancellation.
        """
        with self._lock:
            if self._aborted is None and self._cancelled is None:
                self._aborted = TransferAborted(code, detail)
                send = on_bus
            else:
                send = False
            ended = self._cancelled or self._aborted
        if send:
            self._send_abort(code)
        return ended

    def cancel(self, reason: str, abort_code: Optional[int] = None) -> None:
        """End the running transfer at once; send ``abort_code`` if it had started."""
        with self._lock:
            self.cancels += 1
            self._cancel_reason = reason
            if self._cancelled is None:
                self._cancelled = TransferCancelled(reason)
                self._abort_on_cancel = abort_code
        responses = self.responses
        if responses is not None:
            responses.put((time.monotonic(), _Cancel))

    # canopen calls these four from its transfer streams.

    @prompt
    def on_response(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Queue a response frame with ``timestamp``: when the receive path took it."""
        responses = self.responses
        if responses is not None:
            frame = bytes(data)
            if len(frame) >= 8 and frame[0] == _ABORT:  # noted for a block download
                self._device_aborts.append((timestamp, struct.unpack_from('<L', frame, 4)[0]))
            responses.put((timestamp, frame))

    def send_request(self, request) -> None:
        """Send a request frame, unless the transfer has already ended.

        Called for every segment of a block (37,450 times for a 256 KiB program image), so
        it takes no lock: what it sets is the transfer's thread's alone, and what other
        threads set (an abort, a cancellation) is a single attribute, looked at before each
        frame as before.
        """
        if self._kind is None:  # the transfer's first request
            self._kind = request[0] >> 5
            self._sent_at = self._began = time.monotonic()
        else:
            self._sent_at = time.monotonic()
        self._raise_if_ended()
        if self._device_aborts and self._kind == _CCS_BLOCK_DOWNLOAD and self.initiated:
            self._raise_device_abort()
        self.network.send_message(self.rx_cobid, request)
        self._sent_any = True

    def request_response(self, sdo_request) -> bytes:
        """Send a request and return the response that answers it."""
        initiating = self._kind is None
        self.send_request(sdo_request)
        return self._await(self._expectation(sdo_request, initiating), initiating)

    def read_response(self) -> bytes:
        """Return the next frame of a block transfer (no request goes before it)."""
        if self._kind == _CCS_BLOCK_DOWNLOAD:
            return self._await(_block_download_ack)
        return self._await(_any_frame)

    def abort(self, abort_code: int = abort_codes.GENERAL_ERROR) -> None:
        """Abort the transfer on the bus, once; later aborts keep the first code.

        A transfer of which nothing was sent is ended without a frame: the device never
        heard of it.
        """
        self.fail(abort_code, '', on_bus=self._sent_any)

    def _raise_if_ended(self) -> None:
        """Raise the end of the transfer, if it has ended; a cancellation aborts it once."""
        if self._cancelled is None and self._aborted is None:
            return  # before every frame of a block: no lock while nothing has ended
        with self._lock:
            ended = self._cancelled or self._aborted
            code, self._abort_on_cancel = self._abort_on_cancel, None
        if ended is None:
            return
        if ended is self._cancelled and code is not None and self._sent_any:
            self._send_abort(code)
        raise ended

    # The checks.

    def _raise_device_abort(self) -> None:
        """Raise the device's abort if one arrived during this transfer (a block under way).

        The frames stay queued: what is not an abort is awaited as before.
        """
        code = next((code for arrived, code in self._device_aborts if arrived > self._began),
                    None)
        if code is not None:
            with self._lock:
                if self._aborted is None:
                    self._aborted = TransferAborted(code)
                raise self._aborted

    def _send_abort(self, code: int) -> None:
        frame = bytearray(8)
        frame[0] = _ABORT
        _MUX.pack_into(frame, 1, *self._mux)
        struct.pack_into('<L', frame, 4, code)
        try:
            self.network.send_message(self.rx_cobid, frame)
        except Exception:  # noqa: BLE001, S110 - the transfer is over either way
            pass

    def _expectation(self, request, initiating: bool) -> Callable[[bytes], Verdict]:
        ccs = request[0] >> 5
        if initiating:
            accepted = _INITIATE_ANSWERS.get(ccs)
            if accepted is None:
                return _any_frame
            return lambda frame: _initiate_answer(frame, self._mux, accepted)
        if ccs == _CCS_DOWNLOAD_SEGMENT and self._kind == _CCS_DOWNLOAD:
            return _segment_answer(0x20, request[0] & _TOGGLE)
        if ccs == _CCS_UPLOAD_SEGMENT:
            return _segment_answer(0x00, request[0] & _TOGGLE)
        if self._kind == _CCS_BLOCK_DOWNLOAD:
            return _block_download_end
        return _any_frame

    def _await(self, expected: Callable[[bytes], Verdict], initiating: bool = False) -> bytes:
        while True:
            deadline = (self._deadline if self._answer_within is None
                        else self._sent_at + self._answer_within)
            remaining = deadline - time.monotonic()
            try:
                arrived, frame = self.responses.get(timeout=max(remaining, 0.0))
            except queue.Empty:
                detail = 'the device did not answer in time'
                if self.ignored_frames:
                    detail += (f'; {self.ignored_frames} frame(s) that did not answer this '
                               f'request were ignored')
                raise self.fail(abort_codes.TIMEOUT, detail) from None
            if frame is _Cancel:
                self._raise_if_ended()
                continue
            if len(frame) < 8 or arrived <= (self._began if frame[0] == _ABORT
                                             else self._sent_at):
                self.ignored_frames += 1
                continue
            if frame[0] == _ABORT:
                code, = struct.unpack_from('<L', frame, 4)
                # An abort naming another object answers an earlier request, not this one;
                # nor does "unknown command" of 0000:00 answer an expedited or segmented
                # initiation, which every SDO server knows: it answers a stray frame (the
                # rest of a block that reached a device restarted meanwhile).
                named = _MUX.unpack_from(frame, 1)
                if initiating and (named not in (self._mux, (0, 0)) or (
                        named == (0, 0) and code == abort_codes.UNKNOWN_COMMAND
                        and self._kind in (_CCS_UPLOAD, _CCS_DOWNLOAD))):
                    self.ignored_frames += 1
                    continue
                with self._lock:
                    if self._aborted is None:
                        self._aborted = TransferAborted(code)
                    raise self._aborted
            verdict = expected(frame)
            if verdict is None:
                self.initiated = self.initiated or initiating
                return frame
            if verdict == IGNORE:
                self.ignored_frames += 1
                continue
            raise self.fail(verdict, f'unexpected answer 0x{frame[0]:02X} from the device')


class DownloadStream(WritableStream):
    """canopen's segmented/expedited download stream, which sends its end frame only once.

    A stream whose initiation failed, or that is closed already, sends nothing when it is
    closed (again) by garbage collection.
    """

    def __init__(self, sdo_client, index: int, subindex: int = 0, size: Optional[int] = None):
        self._initiated = False
        super().__init__(sdo_client, index, subindex, size)
        self._initiated = True

    def close(self) -> None:
        """Close the stream, sending the end of a segmented download if it is due."""
        if self.closed:
            return
        if not self._initiated:
            io.RawIOBase.close(self)
            return
        super().close()


def _any_frame(_frame: bytes) -> Verdict:
    return None


# Server answers to each initiating request: (mask, value) pairs of the first byte.
_INITIATE_ANSWERS = {
    _CCS_DOWNLOAD: ((0xFF, 0x60),),
    _CCS_UPLOAD: ((0xE0, 0x40),),
    # Block upload: bit 2 says CRC, bit 1 says a size follows, bit 0 is the subcommand.
    _CCS_BLOCK_UPLOAD: ((0xE1, 0xC0),),
    _CCS_BLOCK_DOWNLOAD: ((0xE3, 0xA0),),
}


def _initiate_answer(frame: bytes, mux, accepted) -> Verdict:
    if _MUX.unpack_from(frame, 1) != mux:
        return IGNORE  # for another object: a late answer to an earlier request
    if accepted is _INITIATE_ANSWERS[_CCS_BLOCK_UPLOAD] and frame[0] & 0xE0 == 0x40:
        # CiA 301 lets a server answer a block upload request with a normal upload
        # response, which canopen's block stream cannot continue: end it, as a refusal.
        return abort_codes.UNKNOWN_COMMAND
    if not any(frame[0] & mask == value for mask, value in accepted):
        return IGNORE
    if frame[0] & 0xE3 == 0xA0 and not 1 <= frame[4] <= 127:
        return abort_codes.BLOCK_SIZE
    return None


def _segment_answer(scs_bits: int, toggle: int) -> Callable[[bytes], Verdict]:
    def check(frame: bytes) -> Verdict:
        if frame[0] & 0xE0 != scs_bits:
            return abort_codes.UNKNOWN_COMMAND
        if frame[0] & _TOGGLE != toggle:
            return abort_codes.TOGGLE_BIT
        return None
    return check


def _block_download_ack(frame: bytes) -> Verdict:
    if frame[0] & 0xE3 != 0xA2:
        return abort_codes.UNKNOWN_COMMAND
    if not 1 <= frame[2] <= 127:
        return abort_codes.BLOCK_SIZE
    return None


def _block_download_end(frame: bytes) -> Verdict:
    if frame[0] & 0xE3 != 0xA1:
        return abort_codes.UNKNOWN_COMMAND
    return None


def close_without_frames(stream) -> None:
    """Mark a canopen stream closed without its closing frames and log lines, now and later.

    For a stream whose transfer already ended with an abort: its own ``close()`` would send
    the end of the transfer (or log it), and garbage collection would call it again.
    """
    io.RawIOBase.close(stream)


def upload_finished(stream) -> bool:
    """Return whether the device has sent the last segment of the upload on ``stream``."""
    return getattr(stream, '_done', True)
