"""How a command fails: a command line that cannot be carried out, a refusal of the gateway."""

import sys

from ..client import describe


class UsageError(Exception):
    """The command line cannot be carried out: an unknown name, a value that does not fit."""


def print_refusal(response) -> int:
    """Print what the gateway refused: the abort code, its name and meaning, or why."""
    kind = 'SDO abort ' if getattr(response, 'abort_code', 0) else ''
    print(f'error: {kind}{describe(response)}', file=sys.stderr)
    return 1
