"""Argument types the command groups share: numbers in a range, seconds, a node id."""

import argparse
import math

from ...core.protocol import MAX_NODE_ID
from ...core.text import quoted
from ...core.values import parse_integer


def integer(text: str) -> int:
    """Parse a number: decimal, or with a 0x/0o/0b prefix (as ``int(text, 0)``)."""
    try:
        return parse_integer(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def ranged(name: str, lowest: int, highest: int, hex_digits: int = 0):
    """Return an argparse type: an integer in ``lowest..highest``."""
    def parse(text: str) -> int:
        value = integer(text)
        if not lowest <= value <= highest:
            shown = (f'0x{lowest:0{hex_digits}X}..0x{highest:0{hex_digits}X}' if hex_digits
                     else f'{lowest}..{highest}')
            raise argparse.ArgumentTypeError(f'{name} {text} is out of range: allowed {shown}')
        return value
    parse.__name__ = name  # argparse names the type in its messages
    return parse


def seconds(text: str) -> float:
    """Parse a number of seconds (any but NaN); each command bounds it as it needs."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a number of seconds') from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a number of seconds')
    return value


def bounded_seconds(highest: float, zero_means: str):
    """Return a parser of a timeout from 0 (``zero_means``, in words) to ``highest`` s."""
    def parse(text: str) -> float:
        value = seconds(text)
        if not 0.0 <= value <= highest:
            raise argparse.ArgumentTypeError(
                f'timeout {quoted(text)} is out of range: allowed 0 ({zero_means}) to '
                f'{highest:g} s')
        return value
    return parse


def positive_seconds(text: str) -> float:
    """Parse a number of seconds more than 0."""
    value = seconds(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f'{quoted(text)} must be more than 0 s')
    return value


node_id = ranged('node', 0, MAX_NODE_ID)
