"""Write protection for integrators: which SDO writes and NMT commands may reach the bus.

A refused write is answered with abort code 0x08000021 ("data cannot be transferred or
stored to the application because of local control") and never reaches the bus.
"""

from dataclasses import dataclass
from typing import Optional, Tuple

from ..protocol import MAX_NODE_ID

RULE_FORMAT = ("'node:index' or 'node:first-last', node 0..127 or * for any node, "
               "indexes 0x0000..0xFFFF (e.g. '5:0x2000', '*:0x6040-0x60FF')")


@dataclass(frozen=True)
class WriteRule:
    """Writes to ``first..last`` of ``node_id`` (None = any node) are allowed."""

    node_id: Optional[int]
    first: int
    last: int

    def allows(self, node_id: int, index: int) -> bool:
        """Return whether this rule allows writing ``index`` of ``node_id``."""
        return self.node_id in (None, node_id) and self.first <= index <= self.last


def parse_rule(text: str) -> WriteRule:
    """Parse one rule; raise ValueError saying what is wrong (the caller names the rule)."""
    try:
        node_text, _, range_text = text.strip().partition(':')
        node_id = None if node_text.strip() == '*' else int(node_text, 0)
        first_text, dash, last_text = range_text.partition('-')
        first = int(first_text, 0)
        last = int(last_text, 0) if dash else first
    except ValueError:
        raise ValueError('not of the form node:index or node:first-last') from None
    if node_id is not None and not 0 <= node_id <= MAX_NODE_ID:
        raise ValueError(f'node {node_id} is out of range 0..127')
    if not 0 <= first <= last <= 0xFFFF:
        raise ValueError('index range must be within 0x0000..0xFFFF, first <= last')
    return WriteRule(node_id, first, last)


@dataclass(frozen=True)
class WriteProtection:
    """What may be written.

    ``read_only`` refuses every write, NMT command and LSS service; otherwise ``rules``, if
    any, list the objects that may be written.
    """

    read_only: bool = False
    rules: Tuple[WriteRule, ...] = ()

    def refuses_write(self, node_id: int, index: int) -> Optional[str]:
        """Return why writing ``index`` of ``node_id`` is refused, or None."""
        if self.read_only:
            return 'the gateway is read-only (parameter read_only)'
        if self.rules and not any(rule.allows(node_id, index) for rule in self.rules):
            return (f'node {node_id} index 0x{index:04X} is not in the allowed writes '
                    f'(parameter sdo.write_allow)')
        return None

    def refuses_nmt(self) -> Optional[str]:
        """Return why NMT commands are refused, or None."""
        if self.read_only:
            return 'the gateway is read-only (parameter read_only): NMT commands are refused'
        return None

    def refuses_lss(self) -> Optional[str]:
        """Return why layer setting services (LSS) are refused, or None."""
        if self.read_only:
            return ('the gateway is read-only (parameter read_only): LSS services, which can '
                    'change node ids and bit rates, are refused')
        return None
