"""A device's objects by the names its EDS or DCF file gives them (canopen parses the file).

Names are those of the file's ParameterName entries, as canopen's ObjectDictionary keeps
them, matched without regard to case. An entry of a record or array is named
``"Object name.Entry name"`` (canopen's qualified name), or by the object's name and the
entry's own name or sub-index.
"""

import difflib
import os
from typing import Callable, Iterator, List, Optional, Union

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from .canopen_gaps.eds_import import EdsError, import_dictionary
from .text import quoted
from .values import parse_integer

PATH_LIMIT = 120  # characters of a path shown in a message
SUGGESTIONS = 5

DictionaryObject = Union[ODVariable, ODRecord, ODArray]


def load(path: str, node_id: Optional[int] = None,
         note: Optional[Callable[[str], None]] = None) -> ObjectDictionary:
    """Parse an EDS or DCF file with canopen; raise ValueError saying what is wrong with it.

    ``node_id`` resolves the $NODEID expressions of a DCF. ``note``, if given, is told once,
    in one line, which objects of the file canopen could not type.
    """
    shown = quoted(path, PATH_LIMIT)
    if not os.path.isfile(path):
        raise ValueError(f'{shown}: ' + ('a directory, not a file' if os.path.isdir(path)
                                         else 'no such file'))
    try:
        imported = import_dictionary(path, node_id or None)
    except EdsError as error:
        raise ValueError(f'{shown} is not an EDS or DCF file canopen can read: {error}') \
            from None
    except OSError as error:
        raise ValueError(f'{shown} cannot be read: {error.strerror}') from None
    if not len(imported.dictionary):
        raise ValueError(f'{shown} defines no objects: is it an EDS or DCF file?')
    if note and imported.skipped:
        note(f'{shown}: {describe_skipped(imported.skipped)}')
    return imported.dictionary


def describe_skipped(skipped) -> str:
    """Return in one line what canopen could not read of a file: the objects, by reason."""
    by_reason = {}
    for name, reason in skipped:
        by_reason.setdefault(reason, []).append(name)
    parts = []
    for reason, names in by_reason.items():
        names = [name for name in names if name]  # '': the file as a whole
        shown = ', '.join(repr(name) for name in names[:SUGGESTIONS])
        more = f' and {len(names) - SUGGESTIONS} more' if len(names) > SUGGESTIONS else ''
        parts.append(f'{shown}{more}: {reason}' if names else reason)
    return '; '.join(parts)


def find(dictionary: ObjectDictionary, name: str, source: str = 'the EDS') -> DictionaryObject:
    """Return the object (or record/array entry, for "Object.Entry") called ``name``.

    Raises ValueError naming ``source`` (the file) and listing close matches.
    """
    names = _names(dictionary)
    if len(name.strip()) > max(map(len, names), default=0):
        # Longer than every name: nothing to look up (and an unbounded input costs nothing).
        raise ValueError(f'no object {quoted(name)} in {source}{_suggestions(name, names)}')
    found = _top_level(dictionary, name)
    if found is not None:
        return found
    # "Object.Entry"; either name may hold dots itself, so try every split.
    for dot in (position for position, character in enumerate(name) if character == '.'):
        parent = _top_level(dictionary, name[:dot])
        if isinstance(parent, (ODRecord, ODArray)):
            member = _entry_by_name(parent, name[dot + 1:])
            if member is not None:
                return member
    raise ValueError(f'no object {quoted(name)} in {source}{_suggestions(name, names)}')


def entry(parent: Union[ODRecord, ODArray], sub: str) -> ODVariable:
    """Return the entry of a record or array named ``sub``: its sub-index or its name.

    Raises ValueError; for an unknown name it lists close matches.
    """
    try:
        subindex = parse_integer(sub)
    except ValueError:
        found = _entry_by_name(parent, sub)
        if found is None:
            names = [variable.name for variable in _entries(parent)]
            raise ValueError(f'{parent.name!r} has no entry {quoted(sub)}'
                              f'{_suggestions(sub, names)}') from None
        return found
    if not 0 <= subindex <= 0xFF:
        raise ValueError(f'sub-index {quoted(sub)} is out of range: allowed 0..255')
    if subindex in parent.subindices:
        return parent.subindices[subindex]
    if isinstance(parent, ODArray) and subindex > 0 and 1 in parent.subindices:
        return parent[subindex]  # canopen makes it from the array's first entry
    raise ValueError(f'{parent.name!r} has no sub-index {subindex} in the EDS: it has '
                     f'{", ".join(str(s) for s in sorted(parent.subindices))}')


def describe_entries(parent: Union[ODRecord, ODArray]) -> str:
    """Return the entries of a record or array as 'sub name, ...' for a message."""
    return ', '.join(f'{variable.subindex} {variable.name!r}' for variable in _entries(parent))


def _top_level(dictionary: ObjectDictionary, name: str) -> Optional[DictionaryObject]:
    wanted = name.strip().casefold()
    return _only([dictionary[index] for index in dictionary
                  if dictionary[index].name.casefold() == wanted], name, 'its index')


def _entry_by_name(parent: Union[ODRecord, ODArray], name: str) -> Optional[ODVariable]:
    wanted = name.strip().casefold()
    return _only([variable for variable in _entries(parent)
                  if variable.name.casefold() == wanted], f'{parent.name}.{name}',
                 'the sub-index')


def _only(matches: List, name: str, instead: str):
    """Return the one match, None for none; refuse a name several objects share."""
    if len(matches) > 1:
        raise ValueError(f'{quoted(name)} is ambiguous: it could be {_places(matches)}; '
                         f'name {instead}')
    return matches[0] if matches else None


def _places(objects: List) -> str:
    """Return where ``objects`` are, as 0x6200:01..08 for a run of one object's entries."""
    index = objects[0].index
    subindices = [getattr(obj, 'subindex', None) for obj in objects]
    if all(obj.index == index for obj in objects) and None not in subindices:
        if subindices == list(range(subindices[0], subindices[-1] + 1)):
            return f'0x{index:04X}:{subindices[0]:02X}..{subindices[-1]:02X}'
        return f'0x{index:04X}:' + ', '.join(f'{sub:02X}' for sub in subindices)
    return ', '.join(f'0x{obj.index:04X}' for obj in objects)


def _entries(parent: Union[ODRecord, ODArray]) -> Iterator[ODVariable]:
    return (parent.subindices[subindex] for subindex in sorted(parent.subindices))


def _names(dictionary: ObjectDictionary) -> list:
    names = []
    for index in dictionary:
        obj = dictionary[index]
        names.append(obj.name)
        if isinstance(obj, (ODRecord, ODArray)):
            names += [variable.qualname for variable in _entries(obj)]
    return names


def _suggestions(name: str, candidates: list) -> str:
    """Return '; did you mean ...?' with the names closest to ``name``, or ''."""
    by_key = {candidate.casefold(): candidate for candidate in candidates}
    wanted = name.strip().casefold()
    close = difflib.get_close_matches(wanted, by_key, n=SUGGESTIONS, cutoff=0.6)
    close += [key for key in by_key if wanted and wanted in key and key not in close]
    if not close:
        return ' (names are matched without regard to case; none is close)'
    return '; did you mean ' + ', '.join(repr(by_key[key]) for key in close[:SUGGESTIONS]) + '?'
