"""SDO requests: what may be asked and what is answered, and the one check of a request.

A request is checked by :func:`refusal` (a batch first by :func:`batch_refusal`) before the
gateway routes it, to its own dictionary or to the device's channel (``channel``).
"""

from dataclasses import dataclass
import math
from typing import Optional, Sequence

from ..protocol import MAX_NODE_ID
from . import abort_codes
from .write_protection import WriteProtection

MAX_TIMEOUT = 60.0

# The largest batch: enough for a full sweep of a device's objects, small enough that one
# answer stays a reasonable message (8 bytes and a short text a result).
MAX_BATCH = 1024


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
        # One shared empty success: every frame a stream sends answers one (results are
        # frozen, so sharing it is safe).
        return cls(True, data=bytes(data)) if data else _DONE

    @classmethod
    def aborted(cls, code: int, detail: str = '') -> 'SdoResult':
        """Return a failed result for abort ``code``, with an optional detail appended."""
        message = abort_codes.describe(code)
        if detail:
            message = f'{message} ({detail})'
        return cls(False, abort_code=code, message=message)

    @classmethod
    def failed(cls, message: str, code: int = 0) -> 'SdoResult':
        """Return a failed result that no device abort explains (refused, bus down, ...)."""
        return cls(False, abort_code=code, message=message)


_DONE = SdoResult(True)


def check_node_id(node_id: int, allowed: str = "0..127 (0 = the gateway's own dictionary)",
                  lowest: int = 0) -> Optional[str]:
    """Return why ``node_id`` is not allowed, or None."""
    if not lowest <= node_id <= MAX_NODE_ID:
        return f'node_id {node_id} is out of range: allowed {allowed}'
    return None


@dataclass(frozen=True)
class Access:
    """One SDO access: a read (upload) or a write (download) of ``index:subindex``."""

    node_id: int
    index: int
    subindex: int
    write: bool = False
    data: bytes = b''
    max_size: int = 0  # reads: largest answer accepted, bytes; 0 = no limit


def one_each(result: SdoResult, count: Optional[int]):
    """Return ``result`` as the answer of a single request (``count`` None) or of a batch.

    A batch refused or failed before it ran gets the same result for each of its accesses.
    """
    return result if count is None else [result] * count


def refusal(access: Access, timeout: float,
            protection: WriteProtection) -> Optional[SdoResult]:
    """Return the answer that refuses ``access`` before anything is sent, or None.

    Its fields first, then write protection, then ``timeout`` (which a batch's accesses
    share, and :func:`batch_refusal` has checked already).
    """
    problem = _field_problem(access)
    if problem:
        return SdoResult.failed(problem)
    if access.write:
        refused = protection.refuses_write(access.node_id, access.index)
        if refused:
            return SdoResult.aborted(abort_codes.LOCAL_CONTROL, refused)
    problem = _timeout_problem(timeout)
    return SdoResult.failed(problem) if problem else None


def batch_refusal(accesses: Sequence[Access], timeout: float) -> Optional[SdoResult]:
    """Return the answer that refuses a whole batch (each access gets it), or None."""
    problem = _timeout_problem(timeout)
    if problem is None and len(accesses) > MAX_BATCH:
        problem = (f'the batch has {len(accesses)} accesses: at most {MAX_BATCH} are '
                   f'allowed; nothing was sent')
    return SdoResult.failed(problem) if problem else None


def _field_problem(access: Access) -> Optional[str]:
    problem = check_node_id(access.node_id)
    if problem:
        return problem
    if not 0 <= access.index <= 0xFFFF:
        return f'index {access.index} is out of range: allowed 0x0000..0xFFFF'
    if not 0 <= access.subindex <= 0xFF:
        return f'subindex {access.subindex} is out of range: allowed 0..255'
    if access.write and not access.data:
        return 'data is empty: write at least 1 byte'
    if not access.write and not 0 <= access.max_size <= 0xFFFFFFFF:
        return (f'max_size {access.max_size} is out of range: allowed 0 (no limit) to '
                f'4294967295')
    return None


def _timeout_problem(timeout: float) -> Optional[str]:
    if math.isnan(timeout) or not 0.0 <= timeout <= MAX_TIMEOUT:
        return (f'timeout {timeout} s is out of range: allowed 0 (use the sdo.timeout '
                f'parameter) up to {MAX_TIMEOUT:g} s')
    return None
