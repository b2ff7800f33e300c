"""canopen 2.4.1's EDS and DCF import, with what it takes to read any vendor's file as it is.

canopen reads most vendors' files as they are; these are the gaps found with real ones, each
closed by :func:`import_dictionary` and listed in docs/library_gaps.md:

1. A negative default of a signed type written in two's-complement hex (an INTEGER16
   ``DefaultValue=0xFFFF`` meaning -1), as many vendors and CiA 306 tools write it, is read as
   unsigned (65535), which no INTEGER16 holds. canopen reads LowLimit and HighLimit of the
   same objects as two's complement already; ``DefaultValue`` and ``ParameterValue`` are read
   the same way here.
2. An array with ``CompactSubObj=N`` gets a sub-index 0 without a value, where CiA 306 says it
   holds N; a record with ``CompactSubObj`` gets no entries at all (and with a names section,
   canopen fails on it): it is read as the array of like entries it describes.
3. An object of a data type canopen does not know is kept as a DOMAIN and logged through
   canopen's logger as it is met, one raw line each; here they are collected, to be said once
   per file (:attr:`ImportedDictionary.skipped`).
4. A file canopen cannot parse raises whatever its parser met (``KeyError``, ``ValueError``,
   configparser's errors) mostly without a line: :class:`EdsError` says the line.
5. canopen opens the file in the machine's locale encoding: a vendor file in Latin-1 (a
   degree sign in a name) fails on a UTF-8 machine, and a byte order mark fails any file. It
   is read as UTF-8 (a byte order mark or not), else Latin-1.
6. Values canopen leaves without a word: ``DefaultValue=$NODEID`` alone and ``0100`` (a
   decimal with a leading zero) get no value, a value its type cannot hold is taken as it is
   (and fails when read). The first are read as written; what no one can read, or what does
   not fit, is left without a value and said with the untyped objects.
7. Type definitions (DEFTYPE, DEFSTRUCT sections with entries) and a DCF commissioning value
   that is not a number (an empty ``Baudrate``) make canopen refuse the whole file: the
   definitions are left out, the value ignored and said.
8. canopen ignores a compact array's ``[xxxxValue]`` section, where a DCF gives its entries'
   values; they are read here.
"""

from configparser import Error as ParserError
from configparser import RawConfigParser
from dataclasses import dataclass, field
import io
import logging
import re
from typing import Iterator, List, Optional, Tuple

import canopen
from canopen.objectdictionary import (
    datatypes,
    ObjectDictionary,
    ODArray,
    ODVariable,
)

REASON_LIMIT = 200  # characters of canopen's own error text in a message
CANOPEN_EDS_LOGGER = 'canopen.objectdictionary.eds'
UNKNOWN_TYPE = re.compile(r'^(?P<name>.*) has an unknown or unsupported data type '
                          r'\((?P<type>0x[0-9A-Fa-f]+)\)$')
OBJECT_SECTION = re.compile(r'^[0-9A-Fa-f]{4}$')
VAR, ARRAY, RECORD = 0x7, 0x8, 0x9  # CiA 306 object types
TYPE_DEFINITIONS = (0x5, 0x6)  # DEFTYPE, DEFSTRUCT
COMMISSIONING = 'DeviceComissioning'  # CiA 306 spells it so
# configparser names the text it read ('<string>'); the line is said already.
CONFIGPARSER_SOURCE = re.compile(r"While reading from '<string>' \[line\s*\d+\]: |"
                                 r"file: '<string>', ")
# Integer data types: (bits, signed)
INTEGER_BITS = {
    datatypes.BOOLEAN: (1, False),
    datatypes.INTEGER8: (8, True), datatypes.INTEGER16: (16, True),
    datatypes.INTEGER24: (24, True), datatypes.INTEGER32: (32, True),
    datatypes.INTEGER40: (40, True), datatypes.INTEGER48: (48, True),
    datatypes.INTEGER56: (56, True), datatypes.INTEGER64: (64, True),
    datatypes.UNSIGNED8: (8, False), datatypes.UNSIGNED16: (16, False),
    datatypes.UNSIGNED24: (24, False), datatypes.UNSIGNED32: (32, False),
    datatypes.UNSIGNED40: (40, False), datatypes.UNSIGNED48: (48, False),
    datatypes.UNSIGNED56: (56, False), datatypes.UNSIGNED64: (64, False)}


class EdsError(ValueError):
    """A file canopen cannot read: the message says the line, where known, and why."""


@dataclass
class ImportedDictionary:
    """A device's object dictionary, and what canopen could not type: (object, reason)."""

    dictionary: ObjectDictionary
    skipped: List[Tuple[str, str]] = field(default_factory=list)


class _Collect(logging.Handler):
    """Keeps canopen's EDS warnings for one import, instead of letting them reach stderr."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: List[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def import_dictionary(path: str, node_id: Optional[int]) -> ImportedDictionary:
    """Return canopen's dictionary of the EDS or DCF file ``path``, its gaps closed.

    ``node_id`` resolves ``$NODEID`` expressions. Raises :class:`EdsError` saying where in
    the file canopen stopped (the line, where known) and why; the caller names the file.
    """
    text = _read_text(path)
    try:
        parser = _parse(text)
    except ParserError as error:
        raise EdsError(_describe(text, error)) from None
    skipped = _prepare(parser, text)
    source = io.StringIO()
    parser.write(source)
    source.seek(0)
    source.name = path  # canopen picks its reader by the name's suffix
    logger = logging.getLogger(CANOPEN_EDS_LOGGER)
    collect = _Collect()
    logger.addHandler(collect)
    propagate, logger.propagate = logger.propagate, False
    try:
        dictionary = canopen.import_od(source, node_id)
    except Exception as error:  # noqa: BLE001 - canopen raises many kinds for a bad file
        raise EdsError(_describe(text, error)) from None
    finally:
        logger.removeHandler(collect)
        logger.propagate = propagate
    skipped += _skipped(collect.messages)
    for variable in _variables(dictionary):
        skipped += _values_as_written(variable, node_id)
    sections = {section.upper(): section for section in parser.sections()}
    for obj in dictionary.values():
        if isinstance(obj, ODArray):
            _compact_count(obj, parser, sections.get(f'{obj.index:04X}'), text)
            skipped += _compact_values(obj, parser, sections.get(f'{obj.index:04X}VALUE'),
                                       node_id)
    return ImportedDictionary(dictionary, skipped)


def _read_text(path: str) -> str:
    """Return the file's text: UTF-8 (with or without a byte order mark), else Latin-1."""
    with open(path, 'rb') as file:
        raw = file.read()
    try:
        return raw.decode('utf-8-sig')
    except UnicodeDecodeError:
        return raw.decode('latin-1')


def _parse(text: str) -> RawConfigParser:
    """Return the file's sections as canopen's parser reads them."""
    parser = RawConfigParser(inline_comment_prefixes=(';',))
    parser.optionxform = str
    parser.read_string(text)
    return parser


def _prepare(parser: RawConfigParser, text: str) -> List[Tuple[str, str]]:
    """Change what canopen would misread or refuse; return what was left out, and why.

    A CompactSubObj record becomes the array of like entries it describes; type definitions
    (DEFTYPE, DEFSTRUCT: canopen fails on their entries) go, as do commissioning values that
    are not numbers (canopen refuses the whole file for an empty ``Baudrate``).
    """
    left_out = []
    for section in parser.sections():
        if not OBJECT_SECTION.match(section):
            continue
        object_type = _number(parser, section, 'ObjectType', text, VAR)
        if object_type in TYPE_DEFINITIONS:
            for sub in [s for s in parser.sections() if s.upper().startswith(section.upper())]:
                parser.remove_section(sub)
        elif (object_type == RECORD and parser.has_option(section, 'CompactSubObj')
              and _number(parser, section, 'CompactSubObj', text, 0)):
            parser.set(section, 'ObjectType', f'0x{ARRAY:X}')
    for section in parser.sections():
        if section.casefold() == COMMISSIONING.casefold():
            for option in ('NodeID', 'Baudrate'):
                value = parser.get(section, option, fallback=None)
                if value is not None and not _is_integer(value):
                    parser.remove_option(section, option)
                    left_out.append((f'[{section}] {option}', f'{value!r} is not a number: '
                                                              'ignored'))
    return left_out


def _number(parser: RawConfigParser, section: str, option: str, text: str,
            missing: int) -> int:
    """Return an option that must be a number; raise :class:`EdsError` with the line if not."""
    value = parser.get(section, option, fallback=None)
    if value is None:
        return missing
    try:
        return int(value, 0)
    except ValueError:
        line = _line_of_section(text, section)
        raise EdsError(f'at line {line}: [{section}] {option}={value!r} is not a number') \
            from None


def _is_integer(value: str) -> bool:
    try:
        int(value, 0)
    except ValueError:
        return False
    return True


def _describe(text: str, error: Exception) -> str:
    """Return where in the file (``text``) reading it went wrong, and why."""
    line = getattr(error, 'lineno', None)
    if line is None and getattr(error, 'errors', None):
        line = error.errors[0][0]  # configparser's ParsingError: (line, text) pairs
    if line is None:
        line = _line_of_section(text, _section_being_read(error))
    reason = CONFIGPARSER_SOURCE.sub('', ' '.join(str(error).split())) or type(error).__name__
    where = f'line {line}' if line else 'somewhere canopen does not say'
    return f'at {where}: {type(error).__name__}: {reason[:REASON_LIMIT]}'


def _section_being_read(error: Exception) -> Optional[str]:
    """Return the section canopen's import was reading when ``error`` was raised, if any."""
    section = None
    trace = error.__traceback__
    while trace is not None:
        if trace.tb_frame.f_code.co_name in ('import_eds', 'build_variable'):
            section = trace.tb_frame.f_locals.get('section', section)
        trace = trace.tb_next
    return section


def _line_of_section(text: str, section: Optional[str]) -> Optional[int]:
    if not section:
        return None
    header = f'[{section}]'.casefold()
    return next((number for number, line in enumerate(text.splitlines(), 1)
                 if line.strip().casefold() == header), None)


def _variables(dictionary: ObjectDictionary) -> Iterator[ODVariable]:
    for obj in dictionary.values():
        if isinstance(obj, ODVariable):
            yield obj
        else:
            yield from obj.subindices.values()


def _values_as_written(variable: ODVariable, node_id: Optional[int]) -> List[Tuple[str, str]]:
    """Read DefaultValue and ParameterValue as vendors write them; return what cannot be.

    canopen reads a signed type's two's-complement hex as unsigned, leaves ``$NODEID`` alone,
    ``0100`` (decimal with a leading zero) and any number it cannot read without a value, and
    takes values its type cannot hold.
    """
    bits, signed = INTEGER_BITS.get(variable.data_type, (None, False))
    if bits is None:
        return []
    left_out = []
    for raw_name, cooked, keyword in (('default_raw', 'default', 'DefaultValue'),
                                      ('value_raw', 'value', 'ParameterValue')):
        raw = getattr(variable, raw_name, None)
        if raw is None or not raw.strip():
            continue
        value = getattr(variable, cooked)
        if value is None:
            try:
                value = _integer(raw, node_id)
            except ValueError:
                left_out.append((variable.qualname, f'{keyword} {raw.strip()!r} is not a '
                                                    'number: left without a value'))
                continue
        hex_written = raw.strip().lower().startswith('0x')
        if signed and hex_written and 1 << (bits - 1) <= value < 1 << bits:
            value -= 1 << bits  # two's complement
        low = -(1 << (bits - 1)) if signed else 0
        if not low <= value < low + (1 << bits):
            left_out.append((variable.qualname, f'{keyword} {raw.strip()!r} does not fit its '
                                                f'type: left without a value'))
            value = None
        setattr(variable, cooked, value)
    return left_out


def _integer(raw: str, node_id: Optional[int]) -> int:
    """Return a CiA 306 integer: hex or decimal terms and ``$NODEID`` added up."""
    total = 0
    for term in raw.replace(' ', '').split('+'):
        if term.upper() == '$NODEID':
            if node_id is None:
                raise ValueError('no node id')
            total += node_id
        elif re.fullmatch(r'-?0[0-9]+', term):
            total += int(term, 10)
        else:
            total += int(term, 0)
    return total


def _compact_count(array: ODArray, parser: RawConfigParser, section: Optional[str],
                   text: str) -> None:
    """Give a CompactSubObj array its sub-index 0: the number of entries, N."""
    if section is None or not parser.has_option(section, 'CompactSubObj'):
        return
    count = _number(parser, section, 'CompactSubObj', text, 0)
    if not 0 <= count <= 0xFE:
        raise EdsError(f'at line {_line_of_section(text, section)}: [{section}] '
                       f'CompactSubObj={count} is out of range: allowed 0..254')
    number = array.subindices[0]
    number.access_type = 'ro'
    number.default = count


def _compact_values(array: ODArray, parser: RawConfigParser, section: Optional[str],
                    node_id: Optional[int]) -> List[Tuple[str, str]]:
    """Give a compact array's entries the values of its ``[xxxxValue]`` section (a DCF's).

    canopen reads the names of a compact array's entries (``[xxxxName]``) but not their
    values; return what of them cannot be read.
    """
    if section is None or 1 not in array.subindices:
        return []
    left_out = []
    for option, raw in parser.items(section):
        if option.casefold() == 'nrofentries':
            continue
        try:
            subindex = int(option, 0)
        except ValueError:
            left_out.append((f'[{section}] {option}', 'not a sub-index: ignored'))
            continue
        entry = array[subindex]
        entry.value_raw, entry.value = raw, None
        left_out += _values_as_written(entry, node_id)
        if subindex not in array.subindices:
            array.add_member(entry)
    return left_out


def _skipped(messages: List[str]) -> List[Tuple[str, str]]:
    skipped = []
    for message in messages:
        unknown = UNKNOWN_TYPE.match(message)
        if unknown:
            skipped.append((unknown['name'], f'data type {unknown["type"]} is not one canopen '
                                             'knows: read and written as raw bytes'))
        else:
            skipped.append(('', message))
    return skipped
