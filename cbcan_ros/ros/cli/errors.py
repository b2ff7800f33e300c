"""How a command fails: a command line that cannot be carried out, a refusal of the gateway."""

import sys

from ..client import describe

# The requests whose abort code is the gateway's refusal, not an SDO abort of a device.
NOT_SDO = ('NMT command', 'state of node')


class UsageError(Exception):
    """The command line cannot be carried out: an unknown name, a value that does not fit."""


def print_refusal(response, what: str = '') -> int:
    """Print what the gateway refused: the abort code, its name and meaning, or why.

    ``what``: the request, as the client names it (``read node 5 object 0x6000:00``). Its
    code is an SDO abort only for an SDO read or write; an NMT command's is a refusal.
    """
    kind = ('SDO abort ' if getattr(response, 'abort_code', 0)
            and not what.startswith(NOT_SDO) else '')
    print(f'error: {f"{what}: " if what else ""}{kind}{describe(response)}', file=sys.stderr)
    return 1
