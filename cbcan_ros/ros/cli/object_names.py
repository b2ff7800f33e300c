"""The object a command names: by index and sub-index, or by its name in the node's EDS."""

from dataclasses import dataclass
import sys
from typing import List, Optional, Tuple

from canopen.objectdictionary import ObjectDictionary, ODVariable

from ...core import eds
from ...core.gateway import own_dictionary
from ...core.text import quoted
from ...core.values import parse_integer
from ..config import device_file_parameter
from .errors import UsageError
from .standalone_client import Client


@dataclass(frozen=True)
class Target:
    """The object a command names; ``variable`` is its EDS entry when it was named by name."""

    node: int
    index: int
    subindex: int
    variable: Optional[ODVariable] = None

    def __str__(self) -> str:
        where = f'node {self.node} object 0x{self.index:04X}:{self.subindex:02X}'
        return f'{where} ({self.variable.qualname})' if self.variable else where


def note(text: str) -> None:
    """Say on stderr, once per file, what canopen could not read of it."""
    print(f'note: {text}', file=sys.stderr)


def _dictionary(client: Client, args) -> Tuple[ObjectDictionary, str]:
    """Return the dictionary that names the objects of ``args.node``, and where it is from."""
    if args.eds:
        try:
            return eds.load(args.eds, args.node, note), quoted(args.eds, eds.PATH_LIMIT)
        except ValueError as error:
            raise UsageError(f'--eds {error}') from None
    if args.node == 0:
        return own_dictionary().object_dictionary, "the gateway's own dictionary"
    name = device_file_parameter(args.node)
    path = client.parameter(name)
    if path is None:
        raise UsageError(f'the gateway {client.gateway} has no parameter {name}: list node '
                         f'{args.node} in its nodes (or node_guarding) parameter and set {name} '
                         f'to its EDS, or give --eds FILE')
    if not path:
        raise UsageError(f"node {args.node} has no EDS: the gateway's parameter {name} is "
                         f'empty; set it, or give --eds FILE')
    try:
        return eds.load(path, args.node, note), quoted(path, eds.PATH_LIMIT)
    except ValueError as error:
        raise UsageError(f"the gateway's parameter {name}: {error} (this command reads the "
                         f'file on this machine; give --eds FILE if it is elsewhere)') from None


def resolve_object(client: Client, args, words: List[str], value_follows: bool
            ) -> Tuple[Target, List[str]]:
    """Resolve OBJECT and the words after it; return the target and the words left over.

    OBJECT is an index, followed by its sub-index (optional for reads), or a name from the
    node's EDS: of one value, or of a record or array followed by the entry's name or
    sub-index.
    """
    try:
        index = parse_integer(args.object)
    except ValueError:
        return resolve_name(client, args, words)
    if not 0 <= index <= 0xFFFF:
        raise UsageError(f'index {quoted(args.object)} is out of range: allowed '
                         f'0x0000..0xFFFF')
    if value_follows and len(words) < 2:
        raise UsageError('an object given by index takes SUBINDEX and VALUE, e.g. '
                         'sdo-write 5 0x2002 0 78563412')
    try:
        subindex = parse_integer(words[0]) if words else 0
    except ValueError as error:
        raise UsageError(f'sub-index: {error}') from None
    if not 0 <= subindex <= 0xFF:
        raise UsageError(f'sub-index {quoted(words[0])} is out of range: allowed 0..255')
    return Target(args.node, index, subindex), words[1:]


def resolve_name(client: Client, args, words: List[str]) -> Tuple[Target, List[str]]:
    """Resolve ``args.object`` as a name in the node's EDS (a record's entry: ``words[0]``)."""
    dictionary, source = _dictionary(client, args)
    try:
        found = eds.find(dictionary, args.object, source)
        if isinstance(found, ODVariable):
            return Target(args.node, found.index, found.subindex, found), words
        if not words:
            raise UsageError(f'{found.name!r} has several entries: name one as '
                             f'"{found.name}.ENTRY" or give its sub-index after the name '
                             f'({eds.describe_entries(found)})')
        variable = eds.entry(found, words[0])
    except ValueError as error:
        raise UsageError(str(error)) from None
    return Target(args.node, variable.index, variable.subindex, variable), words[1:]
