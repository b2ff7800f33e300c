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
   degree sign in a name) fails on a UTF-8 machine. It is read as UTF-8, else Latin-1.
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
SECTION_OF_OBJECT = re.compile(r'^[0-9A-Fa-f]{4}$')
ARRAY, RECORD = 0x8, 0x9  # CiA 306 object types
# configparser names the text it read ('<string>'); the line is said already.
CONFIGPARSER_SOURCE = re.compile(r"While reading from '<string>' \[line\s*\d+\]: |"
                                 r"file: '<string>', ")
SIGNED_BITS = {datatypes.INTEGER8: 8, datatypes.INTEGER16: 16, datatypes.INTEGER24: 24,
               datatypes.INTEGER32: 32, datatypes.INTEGER40: 40, datatypes.INTEGER48: 48,
               datatypes.INTEGER56: 56, datatypes.INTEGER64: 64}


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
    _compact_records_as_arrays(parser)
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
    for variable in _variables(dictionary):
        _signed_from_twos_complement(variable)
    for obj in dictionary.values():
        if isinstance(obj, ODArray):
            _compact_count(obj, parser)
    return ImportedDictionary(dictionary, _skipped(collect.messages))


def _read_text(path: str) -> str:
    """Return the file's text: UTF-8, else Latin-1 (vendors' tools write both)."""
    with open(path, 'rb') as file:
        raw = file.read()
    try:
        return raw.decode('utf-8')
    except UnicodeDecodeError:
        return raw.decode('latin-1')


def _parse(text: str) -> RawConfigParser:
    """Return the file's sections as canopen's parser reads them."""
    parser = RawConfigParser(inline_comment_prefixes=(';',))
    parser.optionxform = str
    parser.read_string(text)
    return parser


def _compact_records_as_arrays(parser: RawConfigParser) -> None:
    """Let canopen read a CompactSubObj record as the array of like entries it describes."""
    for section in parser.sections():
        if (SECTION_OF_OBJECT.match(section) and parser.has_option(section, 'CompactSubObj')
                and int(parser.get(section, 'ObjectType', fallback='0x7'), 0) == RECORD):
            parser.set(section, 'ObjectType', f'0x{ARRAY:X}')


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


def _signed_from_twos_complement(variable: ODVariable) -> None:
    bits = SIGNED_BITS.get(variable.data_type)
    if bits is None:
        return
    for raw, cooked in (('default_raw', 'default'), ('value_raw', 'value')):
        text = (getattr(variable, raw, None) or '').strip().lower()
        value = getattr(variable, cooked)
        if (text.startswith('0x') and isinstance(value, int)
                and 1 << (bits - 1) <= value < 1 << bits):
            setattr(variable, cooked, value - (1 << bits))


def _compact_count(array: ODArray, parser: RawConfigParser) -> None:
    """Give a CompactSubObj array its sub-index 0: the number of entries, N."""
    section = f'{array.index:04X}'
    if not parser.has_option(section, 'CompactSubObj'):
        return
    number = array.subindices[0]
    number.access_type = 'ro'
    number.default = int(parser.get(section, 'CompactSubObj'), 0)


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
