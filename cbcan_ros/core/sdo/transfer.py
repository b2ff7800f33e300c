"""SDO transfers of one access: a read or write run to its end, and its failures as answers.

The device's transfers go through the strict client (``canopen_gaps``); the gateway's own
dictionary (node 0) is read and written in place. Whatever either raises becomes an
:class:`~cbcan_ros.core.sdo.requests.SdoResult` here, and only here.
"""

import logging
from typing import Callable, Optional

import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..bus import BusDown
from ..canopen_gaps.sdo_client import (
    close_without_frames,
    DownloadStream,
    StrictSdoClient,
    TransferAborted,
    TransferCancelled,
    upload_finished,
)
from . import abort_codes
from .requests import Access, SdoResult

LOGGER = logging.getLogger(__name__)


class ObjectTooLarge(Exception):
    """The object is larger than the caller accepts (``max_size``)."""


def check_size(size: int, max_size: int) -> None:
    """Raise :class:`ObjectTooLarge` when ``size`` bytes exceed a non-zero ``max_size``."""
    if max_size and size > max_size:
        raise ObjectTooLarge(f'the object holds {size} bytes, max_size is {max_size}')


def _write_all(stream, data: bytes, written: Optional[Callable[[int], None]] = None) -> None:
    # A raw canopen stream takes at most 7 bytes per write() (one segment): loop.
    view = memoryview(data)
    position = 0
    while position < len(data):
        position += stream.write(view[position:position + 7])
        if written is not None:
            written(position)


def _close_after_failure(client: StrictSdoClient, stream) -> None:
    # The transfer ends with an abort (if the device heard of it); the stream is then marked
    # closed without canopen's closing frames and log lines, now and at garbage collection.
    client.abort(abort_codes.GENERAL_ERROR)
    close_without_frames(stream)


def upload(client: StrictSdoClient, index: int, subindex: int, max_size: int,
           block: bool) -> bytes:
    """Read an object, refusing more than ``max_size`` bytes (0 = no limit).

    The size a device announces is checked before any segment is fetched, so an oversized
    object costs one round trip (aborted with 0x05040005); the bytes that arrive must then
    match the announced size (0x06070012 too many, 0x06070013 too few).
    """
    stream = client.open(index, subindex, 'rb', buffering=0, block_transfer=block)
    try:
        data = _read_all(client, stream, max_size)
    except BaseException:
        _close_after_failure(client, stream)
        raise
    stream.close()
    return data


def _read_all(client: StrictSdoClient, stream, max_size: int) -> bytes:
    expedited = getattr(stream, 'exp_data', None) is not None
    announced = stream.size
    parts = []
    received = 0
    try:
        if announced is not None:
            check_size(announced, max_size)
        while True:
            part = stream.read(7)
            # A segment may carry no data and still say more follow (c = 0): only the
            # stream's own end ends the upload.
            if not part and upload_finished(stream):
                break
            parts.append(part)
            received += len(part)
            check_size(received, max_size)
            if announced is not None and received > announced:
                raise client.fail(abort_codes.DATA_TOO_LONG,
                                  f'the device announced {announced} bytes and sent more')
    except ObjectTooLarge as error:
        raise client.fail(abort_codes.OUT_OF_MEMORY, str(error), on_bus=not expedited) \
            from None
    if announced is not None and received != announced:
        raise client.fail(abort_codes.DATA_TOO_SHORT,
                          f'the device announced {announced} bytes and sent {received}')
    return b''.join(parts)


def download(client: StrictSdoClient, index: int, subindex: int, data: bytes,
             block: bool, written: Optional[Callable[[int], None]] = None) -> None:
    """Write an object (expedited, segmented or block).

    ``written(bytes so far)`` is called after each segment went out (a block's last one once
    the device acknowledged the block); what it raises ends the transfer with an abort.
    """
    if block:
        stream = client.open(index, subindex, 'wb', buffering=0, size=len(data),
                             block_transfer=True)
    else:
        stream = DownloadStream(client, index, subindex, size=len(data))
    try:
        _write_all(stream, data, written)
    except BaseException:
        _close_after_failure(client, stream)
        raise
    stream.close()


def run_guarded(transfer: Callable[[], Optional[bytes]]) -> SdoResult:
    """Run one transfer and turn whatever it raises into an :class:`SdoResult`.

    This is the one place where failures become answers: an abort from the device or from
    the gateway, a timeout, a cancelled transfer, a bus that went away. Nothing raised here
    may reach a ROS callback.
    """
    try:
        return SdoResult.ok(transfer() or b'')
    except TransferAborted as error:
        return SdoResult.aborted(error.code, error.detail)
    except SdoAbortedError as error:
        return SdoResult.aborted(error.code)
    except (TransferCancelled, BusDown) as error:
        return SdoResult.failed(str(error))
    except ObjectTooLarge as error:
        return SdoResult.aborted(abort_codes.OUT_OF_MEMORY, str(error))
    except SdoCommunicationError as error:
        return SdoResult.aborted(abort_codes.GENERAL_ERROR, f'protocol error: {error}')
    except Exception as error:  # noqa: BLE001 - every failure must become an answer
        LOGGER.warning('SDO transfer failed unexpectedly: %r', error)
        return SdoResult.aborted(abort_codes.GENERAL_ERROR,
                                 f'{type(error).__name__}: {error}')


def run_local(dictionary: canopen.LocalNode, access: Access) -> SdoResult:
    """Run ``access`` on the gateway's own object dictionary (node 0): no bus, no queue."""
    if access.write:
        return run_guarded(lambda: dictionary.set_data(
            access.index, access.subindex, access.data, check_writable=True))

    def read() -> bytes:
        data = dictionary.get_data(access.index, access.subindex, check_readable=True)
        check_size(len(data), access.max_size)
        return data
    return run_guarded(read)
