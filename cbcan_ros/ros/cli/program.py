"""The program-download command of ``cbcan_cli``: new firmware into a device, with progress."""

import os
import sys

from action_msgs.msg import GoalStatus

from ...action import ProgramDownload
from ...core.program.download import DOWNLOADING, MAX_PROGRAM
from .arguments import ranged
from .drive import node_argument
from .goals import follow_goal, INTERRUPTED
from .standalone_client import Client

BAR = 30  # characters of the progress bar


class ProgressBar:
    """Shows a download's feedback: a line per phase, a bar while the image goes out.

    On a terminal the bar is redrawn in place; otherwise (a log) it is printed at every
    tenth of the image, so a log stays short.
    """

    def __init__(self):
        self._stream = sys.stdout  # looked up now: a caller may have replaced it
        self._live = self._stream.isatty()
        self._phase = ''
        self._shown = -1  # tenths of the image printed (not live)

    def __call__(self, message) -> None:
        """Take one feedback message of the action."""
        feedback = message.feedback
        if feedback.phase != self._phase:
            self._end_bar()
            self._phase = feedback.phase
            print(feedback.phase, file=self._stream, flush=True)
        if feedback.phase != DOWNLOADING or not feedback.bytes_total:
            return
        share = feedback.bytes_sent / feedback.bytes_total
        text = (f'[{"#" * round(BAR * share):<{BAR}}] {100 * share:5.1f} %  '
                f'{feedback.bytes_sent}/{feedback.bytes_total} bytes  '
                f'{feedback.bytes_per_second / 1024:.1f} KiB/s')
        if self._live:
            print(f'\r{text}', end='', file=self._stream, flush=True)
        elif int(10 * share) > self._shown:
            self._shown = int(10 * share)
            print(text, file=self._stream, flush=True)

    def finish(self) -> None:
        """End the bar's line before the answer is printed."""
        self._end_bar()

    def _end_bar(self) -> None:
        if self._live and self._phase == DOWNLOADING:
            print(file=self._stream, flush=True)


def cmd_program_download(client: Client, args) -> int:
    """Download a program image into a device and start it; Ctrl-C cancels."""
    path = os.path.abspath(args.file)  # the gateway resolves no path against our directory
    goal = ProgramDownload.Goal(node_id=args.node, file=path, program=args.program,
                                expected_software_id=args.expect, start=not args.no_start)
    bar = ProgressBar()
    response, interrupted = follow_goal(
        client, ProgramDownload, 'program_download', goal, bar,
        f'program download to node {args.node}',
        f'node {args.node} may still be being programmed (cbcan_cli states shows it)')
    bar.finish()
    if response is None:
        print('interrupted: nothing was sent', file=sys.stderr)
        return INTERRUPTED
    result = response.result
    if response.status == GoalStatus.STATUS_SUCCEEDED:
        print(f'ok: {result.message}')
        return INTERRUPTED if interrupted else 0
    details = [f'abort code 0x{result.abort_code:08X}'] if result.abort_code else []
    if result.flash_status:
        details.append(f'flash status 0x{result.flash_status:02X}')
    shown = f' ({", ".join(details)})' if details else ''
    kind = 'cancelled' if response.status == GoalStatus.STATUS_CANCELED else 'error'
    print(f'{kind}: node {args.node} program download: {result.message}{shown}',
          file=sys.stderr)
    return INTERRUPTED if interrupted else 1


def add_commands(commands) -> None:
    """Add program-download."""
    download = commands.add_parser(
        'program-download', help='download new firmware into a device (CiA 302-3)',
        description='Download a program image into a device and start it (CiA 302-3): the '
                    'program is stopped and cleared, the image written into 0x1F50, the '
                    'flash awaited (0x1F57), the new program started and its software '
                    'identification (0x1F56) read. Prints each phase and a progress bar. '
                    'The gateway reads FILE: give a path its machine can read. Ctrl-C '
                    'cancels between two blocks; the answer says what the device was left '
                    'in.')
    download.add_argument('node', type=node_argument, metavar='NODE', help='node id 1..127')
    download.add_argument('file', metavar='FILE', help='the program image')
    download.add_argument('--program', type=ranged('program', 1, MAX_PROGRAM), default=1,
                          metavar='N', help='the program number: sub-index of 0x1F50/0x1F51 '
                                            '(default 1)')
    download.add_argument('--expect', type=ranged('software id', 0, 0xFFFFFFFF, 8),
                          default=0, metavar='ID',
                          help='the software identification 0x1F56 must show after the '
                               'start, e.g. 0x00010203 (default 0: not checked)')
    download.add_argument('--no-start', action='store_true',
                          help='write the program, leave it stopped')
    download.set_defaults(run=cmd_program_download)
