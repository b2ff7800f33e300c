"""CiA 301 SDO abort codes: a short symbolic name and the meaning of every code.

The meanings are canopen's own table (``SdoAbortedError.CODES``); this module only adds the
symbolic names that PLC and C programmers know the codes by, so there is one table of meanings.
"""

from canopen.sdo.exceptions import SdoAbortedError

TOGGLE_BIT = 0x05030000
TIMEOUT = 0x05040000
UNKNOWN_COMMAND = 0x05040001
BLOCK_SIZE = 0x05040002
OUT_OF_MEMORY = 0x05040005
WRITE_ONLY = 0x06010001
READ_ONLY = 0x06010002
OBJECT_DOES_NOT_EXIST = 0x06020000
SYSTEM_LENGTH = 0x06040047
DATA_TOO_LONG = 0x06070012
DATA_TOO_SHORT = 0x06070013
SUBINDEX_NOT_EXIST = 0x06090011
VALUE_RANGE_EXCEEDED = 0x06090030
NO_RESOURCE = 0x060A0023
GENERAL_ERROR = 0x08000000
LOCAL_CONTROL = 0x08000021
DEVICE_STATE = 0x08000022

NAMES = {
    0x05030000: 'TOGGLE_BIT',
    0x05040000: 'TIMEOUT',
    0x05040001: 'UNKNOWN_COMMAND',
    0x05040002: 'BLOCK_SIZE',
    0x05040003: 'SEQUENCE_NUMBER',
    0x05040004: 'CRC',
    0x05040005: 'OUT_OF_MEMORY',
    0x06010000: 'UNSUPPORTED_ACCESS',
    0x06010001: 'WRITE_ONLY',
    0x06010002: 'READ_ONLY',
    0x06020000: 'NOT_EXIST',
    0x06040041: 'NO_MAP',
    0x06040042: 'MAP_LENGTH',
    0x06040043: 'PARAMETER_INCOMPATIBLE',
    0x06040047: 'DEVICE_INCOMPATIBLE',
    0x06060000: 'HARDWARE',
    0x06070010: 'TYPE_MISMATCH',
    0x06070012: 'DATA_TOO_LONG',
    0x06070013: 'DATA_TOO_SHORT',
    0x06090011: 'SUBINDEX_NOT_EXIST',
    0x06090030: 'INVALID_VALUE',
    0x06090031: 'VALUE_TOO_HIGH',
    0x06090032: 'VALUE_TOO_LOW',
    0x06090036: 'MAX_LESS_THAN_MIN',
    0x060A0023: 'NO_RESOURCE',
    0x08000000: 'GENERAL',
    0x08000020: 'DATA_TRANSFER',
    0x08000021: 'DATA_LOCAL_CONTROL',
    0x08000022: 'DATA_DEVICE_STATE',
    0x08000023: 'NO_OBJECT_DICTIONARY',
    0x08000024: 'NO_DATA',
}


def describe(code: int) -> str:
    """Return '0xCODE NAME: meaning' for an abort code, naming unknown codes as such."""
    meaning = SdoAbortedError.CODES.get(code)
    if meaning is None:
        return f'0x{code:08X} UNKNOWN: not a CiA 301 abort code (device specific)'
    return f'0x{code:08X} {NAMES[code]}: {meaning}'
