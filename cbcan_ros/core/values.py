"""Values as the bytes of a CANopen object: the one codec of the command-line client.

A value type is a short name for a CiA 301 data type: ``u8`` .. ``u64`` (UNSIGNED8 ..
UNSIGNED64), ``i8`` .. ``i64`` (INTEGER8 .. INTEGER64), ``f32`` and ``f64`` (REAL32,
REAL64), ``str`` (text, UTF-8) and ``hex`` (the bytes as they are on the bus). Numbers are
little-endian, as CANopen sends them. An object's type in an EDS maps onto one of these.
"""

import math
import struct
import sys
from typing import Optional, Sequence, Union

from canopen.objectdictionary import datatypes

from .text import quoted

# The longest number text in range of any type: a 64-bit binary with sign and 0b prefix.
MAX_NUMBER_TEXT = 80

WIDTHS = (8, 16, 24, 32, 40, 48, 56, 64)  # the integer widths of CiA 301

# name: (bytes, signed)
INTEGER_TYPES = {f'{kind}{bits}': (bits // 8, kind == 'i') for kind in 'ui' for bits in WIDTHS}
FLOAT_TYPES = {'f32': '<f', 'f64': '<d'}
VALUE_TYPES = [*INTEGER_TYPES, *FLOAT_TYPES, 'str', 'hex']

# canopen's SIGNED_TYPES and UNSIGNED_TYPES are ordered by width, as WIDTHS is.
_EDS_TYPES = {
    datatypes.BOOLEAN: 'u8',
    **{code: f'i{bits}' for code, bits in zip(datatypes.SIGNED_TYPES, WIDTHS, strict=True)},
    **{code: f'u{bits}' for code, bits in zip(datatypes.UNSIGNED_TYPES, WIDTHS, strict=True)},
    datatypes.REAL32: 'f32',
    datatypes.REAL64: 'f64',
    datatypes.VISIBLE_STRING: 'str',
}
_DATA_TYPE_NAMES = {code: name for name, code in vars(datatypes).items()
                    if name.isupper() and isinstance(code, int)}

Value = Union[int, float, str, bytes]


def int_given_as_float(name: str, value: float) -> Optional[str]:
    """Return why a float64 field's ``value`` looks like a Python int put there, or None.

    rclpy (Jazzy, without ``ROS_PYTHON_CHECK_FIELDS``) serializes an int in a float64 field
    as a tiny number, whatever the int: 5 and 1000 both arrive as 5e-324 (a negative one as
    NaN). No caller means a number below the smallest normal float, so it is refused; the
    number meant cannot be told.
    """
    if not 0 < abs(value) < sys.float_info.min:
        return None
    return (f'{name} {value} is what rclpy sends for a Python int put in a float64 field '
            f'(the number is lost on the way): give it as a float, 5.0 not 5')


def type_of(data_type: Optional[int]) -> str:
    """Return the value type for a CiA 301 data type code (an EDS DataType); hex if none fits.

    Strings other than VISIBLE_STRING, DOMAIN, OCTET_STRING and the time types are shown and
    written as hex bytes.
    """
    return _EDS_TYPES.get(data_type, 'hex')


def data_type_name(data_type: Optional[int]) -> str:
    """Return the CiA 301 name of a data type code, e.g. 'UNSIGNED16'."""
    if data_type is None:
        return 'no DataType'
    return _DATA_TYPE_NAMES.get(data_type, f'DataType 0x{data_type:04X}')


def parse_integer(text: str) -> int:
    """Parse a number: decimal, or with a 0x/0o/0b prefix; raise ValueError naming the text."""
    if len(text) > MAX_NUMBER_TEXT:
        raise ValueError(f'{quoted(text)} is too long for a number ({len(text)} characters)')
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        return int(text, 10)  # '010': decimal with a leading zero, which int(x, 0) refuses
    except ValueError:
        raise ValueError(f'{quoted(text)} is not a number (decimal, or hex as 0x1A2B)') from None


def check_type(value_type: str) -> None:
    """Raise ValueError naming the allowed types when ``value_type`` is none of them."""
    if value_type not in VALUE_TYPES:
        raise ValueError(f'{quoted(str(value_type))} is not a value type: allowed '
                         f'{" ".join(VALUE_TYPES)}')


def size_of(value_type: str) -> Optional[int]:
    """Return the bytes a value of ``value_type`` takes, or None when any size fits."""
    if value_type in INTEGER_TYPES:
        return INTEGER_TYPES[value_type][0]
    if value_type in FLOAT_TYPES:
        return struct.calcsize(FLOAT_TYPES[value_type])
    return None


def integer_range(value_type: str) -> range:
    """Return the numbers an integer type holds."""
    size, signed = INTEGER_TYPES[value_type]
    bits = size * 8
    if signed:
        return range(-(1 << (bits - 1)), 1 << (bits - 1))
    return range(0, 1 << bits)


def encode_value(words: Sequence[str], value_type: str) -> bytes:
    """Turn the words of a value into the bytes to write.

    Raises ValueError with a message for the user when the value does not fit the type.
    """
    check_type(value_type)
    if value_type == 'str':
        data = ' '.join(words).encode('utf-8')
    elif value_type == 'hex':
        data = _hex_bytes(words)
    else:
        if len(words) != 1:
            raise ValueError(f'type {value_type} takes one number, got {len(words)} words')
        if value_type in INTEGER_TYPES:
            data = _integer_bytes(words[0], value_type)
        else:
            data = _float_bytes(words[0], value_type)
    if not data:
        raise ValueError('the value is empty: write at least 1 byte')
    return data


def decode_value(data: bytes, value_type: str) -> Value:
    """Return the value ``data`` holds as ``value_type``.

    Raises ValueError naming the type and the number of bytes when they do not fit.
    """
    check_type(value_type)
    size = size_of(value_type)
    if size is not None and len(data) != size:
        raise ValueError(f'type {value_type} takes {size} byte{"" if size == 1 else "s"}, '
                         f'the answer has {len(data)}')
    if value_type in INTEGER_TYPES:
        return int.from_bytes(data, 'little', signed=INTEGER_TYPES[value_type][1])
    if value_type in FLOAT_TYPES:
        code = FLOAT_TYPES[value_type]
        return _shortest(struct.unpack(code, data)[0], code)
    if value_type == 'str':
        return data.decode('utf-8', errors='backslashreplace')
    return bytes(data)


def _hex_bytes(words: Sequence[str]) -> bytes:
    text = ' '.join(words)
    digits = ''.join(words).replace(':', '').replace(',', '').replace(' ', '')
    if digits.lower().startswith('0x'):
        raise ValueError(f'{quoted(text)}: type hex takes the bytes as on the bus, e.g. '
                         f'78563412 or "78 56 34 12"; for a number give a number type '
                         f'(u32, i16, f32...)')
    try:
        return bytes.fromhex(digits)
    except ValueError:
        raise ValueError(f'{quoted(text)} is not hex bytes (e.g. 78563412 or '
                         f'"78 56 34 12")') from None


def _integer_bytes(word: str, value_type: str) -> bytes:
    number = parse_integer(word)
    allowed = integer_range(value_type)
    if number not in allowed:
        raise ValueError(f'{quoted(word)} does not fit {value_type}: allowed '
                         f'{allowed.start}..{allowed.stop - 1}')
    size, signed = INTEGER_TYPES[value_type]
    return number.to_bytes(size, 'little', signed=signed)


def _float_bytes(word: str, value_type: str) -> bytes:
    try:
        number = float(word)
    except ValueError:
        raise ValueError(f'{quoted(word)} is not a number (e.g. 1.5, -2e-3, inf)') from None
    try:
        return struct.pack(FLOAT_TYPES[value_type], number)
    except (OverflowError, struct.error):
        raise ValueError(f'{quoted(word)} does not fit {value_type}: allowed up to '
                         f'+-3.4e38') from None


def _shortest(number: float, code: str) -> float:
    """Return the shortest decimal that stores as the same bytes (0.1, not 0.10000000149)."""
    if not math.isfinite(number):
        return number
    stored = struct.pack(code, number)
    for digits in range(1, 18):
        candidate = float(f'{number:.{digits}g}')
        if struct.pack(code, candidate) == stored:
            return candidate
    return number


def encode(value: Value, value_type: str) -> bytes:
    """Turn a Python value into the bytes to write as ``value_type``.

    Numbers for the number types, text for ``str``, bytes for ``hex``; text is also taken
    as the command line takes it (``'0x1A'`` for u8, ``'78 56 34 12'`` for hex). Raises
    ValueError with a message for the user when the value does not fit the type.
    """
    if isinstance(value, str):
        return encode_value([value], value_type)
    if isinstance(value, (bytes, bytearray)) and value_type == 'hex':
        return encode_value([bytes(value).hex()], value_type)
    if isinstance(value, int) and not isinstance(value, bool) and value_type in INTEGER_TYPES:
        return encode_value([str(value)], value_type)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and (
            value_type in FLOAT_TYPES):
        return encode_value([repr(float(value))], value_type)
    check_type(value_type)
    raise ValueError(f'type {value_type} does not take {type(value).__name__} {value!r}')
