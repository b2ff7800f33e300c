"""The PLC mailbox command of ``cbcan_cli``: mailbox, one register block executed."""

import sys

from ...plc.mailbox import Cbcan, Me3can
from ...srv import RegisterMailbox
from ..client import answer_within
from .arguments import ranged
from .standalone_client import Client

_word = ranged('word', 0, 0xFFFF, 4)

BLOCK_LENGTHS = {'cbcan': Cbcan.LENGTH, 'me3can': Me3can.LENGTH}


def cmd_mailbox(client: Client, args) -> int:
    """Execute one PLC register block and print the block as returned."""
    words = list(args.words)
    length = BLOCK_LENGTHS.get(args.format or 'cbcan')
    if length and len(words) < length:
        words += [0] * (length - len(words))  # the unwritten registers of the PLC are 0
    response = client.call(RegisterMailbox, 'plc_mailbox', RegisterMailbox.Request(
        format=args.format, registers=words), answer_within(0.0))
    words = list(response.registers)
    for offset in range(0, len(words), 8):
        row = words[offset:offset + 8]
        if args.decimal:
            print(f'{offset:>3}: ' + ' '.join(f'{word:>5}' for word in row))
        else:
            print(f'{offset:>3}: ' + ' '.join(f'0x{word:04X}' for word in row))
    if response.message:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    return 0


def add_commands(commands) -> None:
    """Add mailbox."""
    mailbox = commands.add_parser('mailbox', help='execute one PLC register block',
                                  description='Execute one PLC mailbox block (all its '
                                              'registers) and print the block returned.')
    mailbox.add_argument('format', metavar='FORMAT', help='cbcan or me3can')
    mailbox.add_argument('words', type=_word, nargs='+', metavar='WORD',
                         help='the registers from the first, 0..65535 (decimal or 0x hex); '
                              'a shorter block is padded with zeros to its full length')
    mailbox.add_argument('--decimal', action='store_true', help='print words in decimal')
    mailbox.set_defaults(run=cmd_mailbox)
