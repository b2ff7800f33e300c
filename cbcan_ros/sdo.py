"""SDO transfers: request checks, the guarded transfer functions and one worker per device.

Every transfer runs on the worker thread of its device, so requests to one device are
serialized (a device has one SDO server channel) while different devices run in parallel.
Callers get a ``concurrent.futures.Future`` that always resolves to an :class:`SdoResult`:
every failure of the canopen library, expected or not, becomes an honest error answer here.
"""

from concurrent.futures import Future
from dataclasses import dataclass
import logging
import math
import queue
import threading
from typing import Callable, Optional

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from . import abort_codes

LOGGER = logging.getLogger(__name__)

MAX_NODE_ID = 127
MAX_TIMEOUT = 60.0


@dataclass(frozen=True)
class SdoResult:
    """The one answer every SDO request gets."""

    success: bool
    abort_code: int = 0
    message: str = ''
    data: bytes = b''

    @classmethod
    def ok(cls, data: bytes = b'') -> 'SdoResult':
        """Return a successful result carrying ``data``."""
        return cls(True, data=bytes(data))

    @classmethod
    def aborted(cls, code: int, detail: str = '') -> 'SdoResult':
        """Return a failed result for abort ``code``, with an optional detail appended."""
        message = abort_codes.describe(code)
        if detail:
            message = f'{message} ({detail})'
        return cls(False, abort_code=code, message=message)

    @classmethod
    def invalid(cls, message: str) -> 'SdoResult':
        """Return the answer to a request that was refused before it reached the bus."""
        return cls(False, message=message)


def check_node_id(node_id: int, allowed: str = "0..127 (0 = the gateway's own dictionary)",
                  lowest: int = 0) -> Optional[str]:
    """Return why ``node_id`` is not allowed, or None."""
    if not lowest <= node_id <= MAX_NODE_ID:
        return f'node_id {node_id} is out of range: allowed {allowed}'
    return None


def check_request(node_id: int, index: int, subindex: int, timeout: float) -> Optional[str]:
    """Return why an SDO request is not valid, or None; checked before anything is sent."""
    problem = check_node_id(node_id)
    if problem:
        return problem
    if not 0 <= index <= 0xFFFF:
        return f'index {index} is out of range: allowed 0x0000..0xFFFF'
    if not 0 <= subindex <= 0xFF:
        return f'subindex {subindex} is out of range: allowed 0..255'
    if math.isnan(timeout) or not 0.0 <= timeout <= MAX_TIMEOUT:
        return (f'timeout {timeout} s is out of range: allowed 0 (use the sdo.timeout '
                f'parameter) up to {MAX_TIMEOUT:g} s')
    return None


class ObjectTooLarge(Exception):
    """The object is larger than the caller accepts (``max_size``)."""


def check_size(size: int, max_size: int) -> None:
    """Raise :class:`ObjectTooLarge` when ``size`` bytes exceed a non-zero ``max_size``."""
    if max_size and size > max_size:
        raise ObjectTooLarge(f'the object holds {size} bytes, max_size is {max_size}')


class BlockTransferRefused(Exception):
    """The device refused to initiate a block transfer; nothing was transferred."""

    def __init__(self, device_lacks_block: bool):
        super().__init__('block transfer refused')
        self.device_lacks_block = device_lacks_block


def _is_timeout(error: SdoCommunicationError) -> bool:
    return 'No SDO response' in str(error)


def _open(client, index: int, subindex: int, mode: str, block: bool, **kwargs):
    """Open a transfer stream; a refused block initiation raises BlockTransferRefused.

    A device without block support either aborts the initiation (0x05040001) or, as CiA 301
    allows for uploads, answers with a normal upload response, which canopen's block client
    cannot take and aborts. Neither moved any data, so the caller may repeat it segmented.
    """
    if not block:
        return client.open(index, subindex, mode, buffering=0, **kwargs)
    try:
        return client.open(index, subindex, mode, buffering=0, block_transfer=True, **kwargs)
    except SdoAbortedError as error:
        raise BlockTransferRefused(error.code == abort_codes.UNKNOWN_COMMAND) from error
    except SdoCommunicationError as error:
        if _is_timeout(error):
            raise
        raise BlockTransferRefused(True) from error


def upload(client, index: int, subindex: int, max_size: int, block: bool) -> bytes:
    """Read an object through a canopen ``SdoClient``, refusing more than ``max_size`` bytes.

    The size a device announces is checked before any segment is fetched, so an oversized
    object costs one round trip; the transfer is then aborted on the bus with 0x05040005.
    """
    stream = _open(client, index, subindex, 'rb', block)
    try:
        announced = stream.size
        if announced is not None:
            check_size(announced, max_size)
        parts = []
        received = 0
        while True:
            part = stream.read(7)
            if not part:
                break
            parts.append(part)
            received += len(part)
            check_size(received, max_size)
        data = b''.join(parts)
        if announced is not None:
            data = data[:announced]
        return data
    except ObjectTooLarge:
        expedited = getattr(stream, 'exp_data', None) is not None
        if not expedited and not getattr(stream, '_done', False):
            client.abort(abort_codes.OUT_OF_MEMORY)
        raise
    finally:
        stream.close()


def download(client, index: int, subindex: int, data: bytes, block: bool) -> None:
    """Write an object through a canopen ``SdoClient`` (expedited, segmented or block)."""
    if block:
        with _open(client, index, subindex, 'wb', True, size=len(data)) as stream:
            stream.write(data)
    else:
        client.download(index, subindex, data)




def run_guarded(transfer: Callable[[], Optional[bytes]]) -> SdoResult:
    """Run one transfer and turn whatever it raises into an :class:`SdoResult`.

    This is the one place where library failures become answers: an abort from the device,
    a timeout, a malformed frame (canopen lets ``struct.error`` escape for short frames),
    a bus that went away. Nothing raised here may reach a ROS callback.
    """
    try:
        return SdoResult.ok(transfer() or b'')
    except SdoAbortedError as error:
        return SdoResult.aborted(error.code)
    except ObjectTooLarge as error:
        return SdoResult.aborted(abort_codes.OUT_OF_MEMORY, str(error))
    except SdoCommunicationError as error:
        if _is_timeout(error):
            return SdoResult.aborted(abort_codes.TIMEOUT, 'the device did not answer')
        if 'Toggle bit' in str(error):
            return SdoResult.aborted(abort_codes.TOGGLE_BIT)
        return SdoResult.aborted(abort_codes.GENERAL_ERROR, f'protocol error: {error}')
    except Exception as error:  # noqa: BLE001 - every failure must become an answer
        LOGGER.warning('SDO transfer failed unexpectedly: %r', error)
        return SdoResult.aborted(abort_codes.GENERAL_ERROR,
                                 f'{type(error).__name__}: {error}')


class DeviceWorker:
    """Runs the SDO transfers of one device one after another on a thread of its own."""

    def __init__(self, name: str):
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, transfer: Callable[[], Optional[bytes]]) -> 'Future[SdoResult]':
        """Queue a transfer; the future resolves to its :class:`SdoResult`."""
        future: Future = Future()
        self._jobs.put((transfer, future))
        return future

    def stop(self) -> None:
        """Finish the queued transfers, then end the thread."""
        self._jobs.put(None)
        self._thread.join()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            transfer, future = job
            if future.set_running_or_notify_cancel():
                future.set_result(run_guarded(transfer))


class SdoChannel:
    """The SDO server channel of one remote device: its canopen client and its worker.

    Block transfer is tried first when enabled; a device that refuses to initiate one gets
    segmented transfers from then on (nothing was transferred, so falling back is safe even
    for writes).
    """

    def __init__(self, client, name: str, block_transfer: bool):
        self._client = client
        self._client.MAX_RETRIES = 1  # one request only: a write is never sent twice
        self._worker = DeviceWorker(name)
        self._block = block_transfer

    def read(self, index: int, subindex: int, max_size: int,
             timeout: float) -> 'Future[SdoResult]':
        """Queue an upload of ``index:subindex``."""
        return self._worker.submit(lambda: self._with_block_fallback(
            timeout, lambda block: upload(self._client, index, subindex, max_size, block)))

    def write(self, index: int, subindex: int, data: bytes,
              timeout: float) -> 'Future[SdoResult]':
        """Queue a download of ``data`` to ``index:subindex``."""
        return self._worker.submit(lambda: self._with_block_fallback(
            timeout, lambda block: download(self._client, index, subindex, data, block)))

    def stop(self) -> None:
        """Finish queued transfers and end the worker."""
        self._worker.stop()

    def _with_block_fallback(self, timeout: float, transfer: Callable[[bool], Optional[bytes]]):
        self._client.RESPONSE_TIMEOUT = timeout
        if self._block:
            try:
                return transfer(True)
            except BlockTransferRefused as refusal:
                self._block = not refusal.device_lacks_block
        return transfer(False)


def resolved(result: SdoResult) -> 'Future[SdoResult]':
    """Return a future that already holds ``result`` (for answers that need no bus)."""
    future: Future = Future()
    future.set_result(result)
    return future
