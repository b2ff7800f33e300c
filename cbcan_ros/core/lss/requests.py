"""Layer setting services (CiA 305): what may be asked of devices, and what is answered.

Requests are checked here before the LSS master (``master``) queues them; its frames
are in ``frames``.
"""

from dataclasses import dataclass
import math
from typing import Optional, Tuple

from canopen import lss as cia305

from ..protocol import MAX_NODE_ID

UNCONFIGURED = 0xFF

# CiA 305's bit timing table: bit/s to the index a device is sent (5 is reserved).
BIT_TIMING = {1000000: 0, 800000: 1, 500000: 2, 250000: 3, 125000: 4, 50000: 6, 20000: 7,
              10000: 8}

DEFAULT_TIMEOUT = 5.0  # configure and inquire
MAX_TIMEOUT = 600.0

ERRORS = {
    cia305.CS_CONFIGURE_NODE_ID: {1: 'node id out of range'},
    cia305.CS_CONFIGURE_BIT_TIMING: {1: 'bit timing (bit rate) not supported'},
    cia305.CS_STORE_CONFIGURATION: {1: 'storing the configuration is not supported',
                                    2: 'storage media access error'},
}
WHAT = {cia305.CS_CONFIGURE_NODE_ID: 'configure node id',
        cia305.CS_CONFIGURE_BIT_TIMING: 'configure bit timing',
        cia305.CS_STORE_CONFIGURATION: 'store configuration'}


@dataclass(frozen=True)
class Identity:
    """A device's LSS address: object 0x1018:1..4."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int

    def parts(self) -> Tuple[int, int, int, int]:
        """Return the four numbers in LSS order."""
        return self.vendor_id, self.product_code, self.revision, self.serial

    def problem(self) -> Optional[str]:
        """Return why this identity cannot be sent, or None."""
        for name, value in zip(('vendor_id', 'product_code', 'revision', 'serial'),
                               self.parts(), strict=True):
            if not 0 <= value <= 0xFFFFFFFF:
                return (f'identity.{name} {value} is out of range: allowed 0..0xFFFFFFFF '
                        f'(object 0x1018 of the device)')
        return None

    def __str__(self) -> str:
        return (f'vendor 0x{self.vendor_id:08X} product 0x{self.product_code:08X} '
                f'revision 0x{self.revision:08X} serial 0x{self.serial:08X}')


@dataclass(frozen=True)
class LssResult:
    """The one answer of every LSS call; fields a service does not have stay empty."""

    success: bool
    message: str = ''
    error_code: int = 0        # configure: the device's LSS error code
    node_id: int = 0           # inquire: the device's node id (255 unconfigured)
    devices: Tuple[Identity, ...] = ()
    node_ids: Tuple[int, ...] = ()


def check_timeout(timeout: float) -> Optional[str]:
    """Return why an LSS call's timeout is not valid, or None."""
    if math.isnan(timeout) or not 0.0 <= timeout <= MAX_TIMEOUT:
        return (f'timeout {timeout} s is out of range: allowed 0 (a default that fits the '
                f'bus) up to {MAX_TIMEOUT:g} s')
    return None


def scan_problem(first_node_id: int, timeout: float) -> Optional[str]:
    """Return why a scan request is not valid, or None."""
    if not 0 <= first_node_id <= MAX_NODE_ID:
        return (f'first_node_id {first_node_id} is out of range: allowed 1..127 (ids are '
                f'given from there upward), or 0 to only find one device')
    return check_timeout(timeout)


def configure_problem(identity: Identity, node_id: int, bitrate: int, store: bool,
                      timeout: float) -> Optional[str]:
    """Return why a configure request is not valid, or None."""
    if not 0 <= node_id <= MAX_NODE_ID:
        return f'node_id {node_id} is out of range: allowed 1..127, or 0 to keep it'
    if bitrate and bitrate not in BIT_TIMING:
        rates = ', '.join(str(rate) for rate in BIT_TIMING)
        return (f'bitrate {bitrate} is not in the CiA 305 table: allowed {rates}, or 0 to '
                f'keep it')
    if bitrate and not store:
        return (f'bitrate {bitrate} needs store: true: a new bit rate takes effect when the '
                f'device starts again with its stored configuration (the gateway does not '
                f'switch the bus to another rate)')
    if not (node_id or bitrate or store):
        return 'nothing to configure: give node_id, bitrate or store'
    return identity.problem() or check_timeout(timeout)


def describe_error(command: int, code: int) -> str:
    """Return a device's LSS error code in words, e.g. 'LSS error 1 (node id out of range)'."""
    if code == cia305.ERROR_VENDOR_SPECIFIC:
        return 'LSS error 255 (manufacturer-specific)'
    meaning = ERRORS.get(command, {}).get(code, 'reserved')
    return f'LSS error {code} ({meaning})'
