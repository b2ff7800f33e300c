"""How a command fails: a command line that cannot be carried out, a refusal of the gateway."""

import sys

from ..client import describe


class UsageError(Exception):
    """The command line cannot be carried out: an unknown name, a value that does not fit."""


def print_refusal(response, what: str = '') -> int:
    """Print what the gateway refused: the abort code, its name and meaning, or why.

    ``what``: the request, as the client names it (``read node 5 object 0x6000:00``).
    """
    kind = 'SDO abort ' if getattr(response, 'abort_code', 0) else ''
    print(f'error: {f"{what}: " if what else ""}{kind}{describe(response)}', file=sys.stderr)
    return 1
