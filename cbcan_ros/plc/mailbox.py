"""PLC register mailboxes: the register blocks of PLC CANopen master modules, on the gateway.

A PLC program fills a block of 16-bit registers and triggers it; the gateway executes the block
and hands it back as the module would. Two formats are kept (docs/plc_mailbox_formats.md):

* ``cbcan``: Fatek FBs-CBCAN, R3700..R3769 (70 words), SDO read/write and NMT.
* ``me3can``: Mitsubishi ME3CAN1-L command interface, buffer memory G1000..G1066 (67 words),
  single SDO read, multi SDO read and multi SDO write.

This is a translator only: every SDO and NMT service goes through the :class:`Gateway` core.
Data bytes are packed into registers little-endian: byte 2k is the low byte of word k.
"""

import logging

from ..core import nmt
from ..core.protocol import MAX_NODE_ID
from ..core.sdo import abort_codes
from ..core.text import quoted

LOGGER = logging.getLogger(__name__)

Block = list[int]
Answer = tuple[Block, str]

WORD = 0xFFFF

# cbcan R3701: the commands are decimal; the hexadecimal look-alikes are accepted as aliases.
CBCAN_SDO_READ = 5055
CBCAN_SDO_WRITE = 5066
CBCAN_COMMANDS = {5055: CBCAN_SDO_READ, 0x5055: CBCAN_SDO_READ,
                  5066: CBCAN_SDO_WRITE, 0x5066: CBCAN_SDO_WRITE}

# cbcan R3706 of an NMT command (0x1F82): either code of each pair -> the CiA 301 specifier.
CBCAN_NMT_COMMANDS = {
    5: nmt.START, nmt.START: nmt.START,
    4: nmt.STOP, nmt.STOP: nmt.STOP,
    127: nmt.ENTER_PRE_OPERATIONAL, nmt.ENTER_PRE_OPERATIONAL: nmt.ENTER_PRE_OPERATIONAL,
    6: nmt.RESET_NODE, nmt.RESET_NODE: nmt.RESET_NODE,
    7: nmt.RESET_COMMUNICATION, nmt.RESET_COMMUNICATION: nmt.RESET_COMMUNICATION,
}


def words_from_bytes(data: bytes, count: int) -> Block:
    """Pack ``data`` into ``count`` words, low byte first, the rest filled with zeros."""
    padded = bytes(data) + bytes(2 * count - len(data))
    return [padded[2 * k] | padded[2 * k + 1] << 8 for k in range(count)]


def bytes_from_words(words: list[int], size: int) -> bytes:
    """Unpack the first ``size`` bytes of ``words`` (byte 2k = low byte of word k)."""
    data = bytearray()
    for word in words:
        data += bytes((word & 0xFF, word >> 8 & 0xFF))
    return bytes(data[:size])


def abort_words(code: int) -> Block:
    """Return an SDO abort code as two words, low word first."""
    return [code & WORD, code >> 16 & WORD]


def _object(node_id: int, index: int, subindex: int) -> str:
    return f'node {node_id} object 0x{index:04X}:{subindex}'


class _Translator:
    """What both formats share: the core, the completion callable and the two SDO calls."""

    def __init__(self, gateway, completion):
        self._gateway = gateway
        self._completion = completion

    async def _read(self, node_id: int, index: int, subindex: int, max_size: int):
        return await self._completion(
            self._gateway.sdo_read(node_id, index, subindex, max_size=max_size))

    async def _write(self, node_id: int, index: int, subindex: int, data: bytes):
        return await self._completion(self._gateway.sdo_write(node_id, index, subindex, data))

    @staticmethod
    def _abort_code(result) -> int:
        """Return the abort code of a failed result; a refusal without one is GENERAL_ERROR."""
        return result.abort_code or abort_codes.GENERAL_ERROR


class Cbcan(_Translator):
    """Fatek FBs-CBCAN: R3700..R3769, execute flag 0xCA0E, result code in R3700."""

    LENGTH = 70
    REGISTERS = 'R3700..R3769'
    EXECUTE_FLAG = 0xCA0E
    SDO_READ = CBCAN_SDO_READ
    SDO_WRITE = CBCAN_SDO_WRITE

    OK = 0
    CMD_CODE_ERR = 1
    NODE_ID_ERR = 2
    SDO_EXEC_ERR = 4

    RESULT, COMMAND, NODE, INDEX, SUBINDEX, SIZE, DATA = range(7)
    DATA_WORDS = 64
    MAX_SIZE = 128

    NMT_COMMAND_INDEX = 0x1F82
    NMT_STATE_INDEX = 0x300C
    ALL_NODES = 128
    NMT_STATE_SIZE = 2  # the state is answered as one whole data word

    async def execute(self, block: Block) -> Answer:
        """Execute a checked 70-word block; return it as the PLC reads it back."""
        if block[self.RESULT] != self.EXECUTE_FLAG:
            return block, (f'R3700 = 0x{block[self.RESULT]:04X} is not the execute flag '
                           f'0x{self.EXECUTE_FLAG:04X}: nothing was executed')
        command = CBCAN_COMMANDS.get(block[self.COMMAND])
        if command is None:
            return self._result(block, self.CMD_CODE_ERR), (
                f'R3701 = {block[self.COMMAND]} is not a command: 5055 (SDO read) or '
                f'5066 (SDO write), also accepted as 0x5055 and 0x5066')
        index = block[self.INDEX]
        if command == self.SDO_WRITE and index == self.NMT_COMMAND_INDEX:
            return self._nmt_command(block)
        if command == self.SDO_READ and index == self.NMT_STATE_INDEX:
            return self._nmt_state(block)
        return await self._sdo(block, command == self.SDO_READ)

    def failed(self, block: Block, message: str) -> Answer:
        """Answer an unexpected failure: result 4 with GENERAL_ERROR."""
        return self._aborted(block, abort_codes.GENERAL_ERROR), message

    def _result(self, block: Block, code: int) -> Block:
        answer = list(block)
        answer[self.RESULT] = code
        return answer

    def _aborted(self, block: Block, code: int) -> Block:
        answer = self._result(block, self.SDO_EXEC_ERR)
        answer[self.DATA:self.DATA + 2] = abort_words(code)
        return answer

    async def _sdo(self, block: Block, read: bool) -> Answer:
        node_id, index, subindex, size = block[self.NODE:self.DATA]
        if node_id > MAX_NODE_ID:
            return self._result(block, self.NODE_ID_ERR), (
                f'R3702 = {node_id} is not a node id: allowed 0..127 '
                f"(0 = the gateway's own dictionary)")
        if subindex > 0xFF:
            return self._aborted(block, abort_codes.SUBINDEX_NOT_EXIST), (
                f'R3704 = {subindex} is not a sub-index: allowed 0..255')
        if not 1 <= size <= self.MAX_SIZE:
            return self._aborted(block, abort_codes.SYSTEM_LENGTH), (
                f'R3705 = {size} is not a size: allowed 1..{self.MAX_SIZE} bytes '
                f'(answered as 0x{abort_codes.SYSTEM_LENGTH:08X} ABORT_SYS_LENGTH)')
        where = _object(node_id, index, subindex)
        if not read:
            data = bytes_from_words(block[self.DATA:], size)
            result = await self._write(node_id, index, subindex, data)
            if not result.success:
                return (self._aborted(block, self._abort_code(result)),
                        f'SDO write of {size} bytes to {where} failed: {result.message}')
            return self._result(block, self.OK), ''
        result = await self._read(node_id, index, subindex, size)
        if not result.success:
            return (self._aborted(block, self._abort_code(result)),
                    f'SDO read of {where} failed: {result.message}')
        answer = self._result(block, self.OK)
        answer[self.SIZE] = len(result.data)
        answer[self.DATA:] = words_from_bytes(result.data, self.DATA_WORDS)
        return answer, ''

    def _nmt_command(self, block: Block) -> Answer:
        target, code = block[self.SUBINDEX], block[self.DATA]
        if not 1 <= target <= self.ALL_NODES:
            return self._result(block, self.NODE_ID_ERR), (
                f'R3704 = {target}: an NMT command (0x1F82) takes the node id 1..127 '
                f'or 128 for all nodes in the sub-index')
        command = CBCAN_NMT_COMMANDS.get(code)
        if command is None:
            return self._aborted(block, abort_codes.VALUE_RANGE_EXCEEDED), (
                f'R3706 = {code} is not an NMT command: 5/1 start, 4/2 stop, '
                f'127/128 pre-operational, 6/129 reset node, 7/130 reset communication')
        node_id = 0 if target == self.ALL_NODES else target
        result = self._gateway.nmt_command(node_id, command)
        if not result.success:
            return self._aborted(block, self._abort_code(result)), (
                f'NMT {nmt.COMMAND_NAMES[command]} failed: {result.message}')
        return self._result(block, self.OK), ''

    def _nmt_state(self, block: Block) -> Answer:
        node_id, subindex = block[self.NODE], block[self.SUBINDEX]
        if not 1 <= node_id <= MAX_NODE_ID:
            return self._result(block, self.NODE_ID_ERR), (
                f'R3702 = {node_id}: the NMT state (0x300C) is read of a node 1..127')
        if subindex != 0:
            return self._aborted(block, abort_codes.SUBINDEX_NOT_EXIST), (
                f'R3704 = {subindex}: the NMT state (0x300C) has sub-index 0 only')
        state = self._gateway.monitor.status(node_id).state
        if state == nmt.BOOT_UP:
            state = nmt.PRE_OPERATIONAL  # after its boot-up message a node is pre-operational
        answer = self._result(block, self.OK)
        answer[self.SIZE] = self.NMT_STATE_SIZE
        answer[self.DATA:] = [state] + [0] * (self.DATA_WORDS - 1)
        return answer, ''


class Me3can(_Translator):
    """Mitsubishi ME3CAN1-L command interface: G1000..G1066, command code in G1000."""

    LENGTH = 67
    REGISTERS = 'G1000..G1066'
    SDO_READ = 0x0004
    SDO_READ_OK = 0x0005
    MULTI_WRITE = 0x0006
    MULTI_WRITE_OK = 0x0007
    MULTI_WRITE_BLOCK_ERROR = 0x00F7
    MULTI_READ = 0x0008
    MULTI_READ_OK = 0x0009
    MULTI_READ_BLOCK_ERROR = 0x00F9
    ERROR = 0x000F

    COMMAND, NODE, INDEX, SUBINDEX, LENGTH_WORD, DATA = range(6)
    SINGLE_DATA_WORDS = 62
    SINGLE_MAX_SIZE = 124

    FIRST_BLOCK = 1
    BLOCKS = 8
    BLOCK_WORDS = 8
    BLOCK_DATA_WORDS = 4
    BLOCK_MAX_SIZE = 8
    END_OF_LIST = 0xFFFF
    FAILED_NODE = 0x0F00

    async def execute(self, block: Block) -> Answer:
        """Execute a checked 67-word block; return it as the PLC reads it back."""
        command = block[self.COMMAND]
        if command == self.SDO_READ:
            return await self._single_read(block)
        if command in (self.MULTI_READ, self.MULTI_WRITE):
            return await self._multi(block, command == self.MULTI_READ)
        return self.failed(block, (
            f'G1000 = 0x{command:04X} is not a known command: 0x0004 (SDO read), '
            f'0x0006 (multi SDO write), 0x0008 (multi SDO read)'))

    def failed(self, block: Block, message: str) -> Answer:
        """Answer 0x000F in G1000; nothing else changes."""
        answer = list(block)
        answer[self.COMMAND] = self.ERROR
        return answer, message

    async def _single_read(self, block: Block) -> Answer:
        node_id, index = block[self.NODE], block[self.INDEX]
        subindex = block[self.SUBINDEX] & 0xFF  # high byte reserved
        if node_id > MAX_NODE_ID:
            return self.failed(block, f'G1001 = {node_id} is not a node id: allowed 0..127')
        result = await self._read(node_id, index, subindex, self.SINGLE_MAX_SIZE)
        if not result.success:
            return self.failed(block, (f'SDO read of {_object(node_id, index, subindex)} '
                                       f'failed: {result.message}'))
        answer = [self.SDO_READ_OK, node_id, index, subindex, len(result.data)]
        answer += words_from_bytes(result.data, self.SINGLE_DATA_WORDS)
        return answer, ''

    def _accesses(self, block: Block, read: bool) -> tuple[list[int], str | None]:
        """Return the offsets of the listed blocks, or why the list is malformed."""
        offsets = []
        for number in range(self.BLOCKS):
            offset = self.FIRST_BLOCK + number * self.BLOCK_WORDS
            node_id = block[offset]
            if node_id == self.END_OF_LIST:
                break
            register = f'G{1000 + offset}'
            if node_id > MAX_NODE_ID:
                return [], (f'block {number + 1}: {register} = {node_id} is not a node id: '
                            f'allowed 0..127, or 0xFFFF to end the list')
            size = block[offset + 3]
            if not read and not 1 <= size <= self.BLOCK_MAX_SIZE:
                return [], (f'block {number + 1}: G{1003 + offset} = {size} is not a data '
                            f'length: allowed 1..{self.BLOCK_MAX_SIZE} bytes')
            offsets.append(offset)
        if not offsets:
            return [], 'the list is empty: G1001 = 0xFFFF ends it before the first block'
        return offsets, None

    async def _multi(self, block: Block, read: bool) -> Answer:
        offsets, problem = self._accesses(block, read)
        if problem:
            return self.failed(block, problem)
        answer = list(block)
        failures = []
        for offset in offsets:
            node_id, index, subindex, size = block[offset:offset + 4]
            subindex &= 0xFF  # high byte reserved
            data_at = offset + 4
            if read:
                result = await self._read(node_id, index, subindex, self.BLOCK_MAX_SIZE)
            else:
                data = bytes_from_words(block[data_at:data_at + self.BLOCK_DATA_WORDS], size)
                result = await self._write(node_id, index, subindex, data)
            if result.success:
                if read:
                    answer[offset + 3] = len(result.data)
                    answer[data_at:data_at + self.BLOCK_DATA_WORDS] = words_from_bytes(
                        result.data, self.BLOCK_DATA_WORDS)
                continue
            code = self._abort_code(result)
            answer[offset] = self.FAILED_NODE | node_id
            answer[offset + 3] = 0
            answer[data_at:data_at + self.BLOCK_DATA_WORDS] = abort_words(code) + [0, 0]
            number = (offset - self.FIRST_BLOCK) // self.BLOCK_WORDS + 1
            failures.append(f'block {number}: SDO {"read" if read else "write"} of '
                            f'{_object(node_id, index, subindex)} failed: {result.message}')
        if failures:
            answer[self.COMMAND] = self.MULTI_READ_BLOCK_ERROR if read \
                else self.MULTI_WRITE_BLOCK_ERROR
            return answer, '; '.join(failures)
        answer[self.COMMAND] = self.MULTI_READ_OK if read else self.MULTI_WRITE_OK
        return answer, ''


FORMATS = {'cbcan': Cbcan, 'me3can': Me3can}
DEFAULT_FORMAT = 'cbcan'


class Mailbox:
    """Executes PLC register blocks on the gateway, in the format the PLC module uses."""

    def __init__(self, gateway, completion):
        """Translate onto ``gateway``; ``completion`` awaits a concurrent Future's result."""
        self._gateway = gateway
        self._completion = completion

    async def execute(self, block_format: str, registers: list[int]) -> Answer:
        """Execute one register block; return (registers after execution, message).

        The message is empty when all went well. A block that cannot be a block of the
        format (unknown format, wrong length, a value that is no 16-bit word) comes back
        unchanged with the reason in the message. Nothing raised escapes.
        """
        registers = list(registers)
        name = block_format or DEFAULT_FORMAT
        translator_type = FORMATS.get(name)
        if translator_type is None:
            return registers, (f'unknown format {quoted(block_format)}: allowed "cbcan" '
                               f'(Fatek FBs-CBCAN, {Cbcan.LENGTH} registers, the default '
                               f'when empty) or "me3can" (Mitsubishi ME3CAN1-L, '
                               f'{Me3can.LENGTH} registers)')
        if len(registers) != translator_type.LENGTH:
            return registers, (f'format {name} takes {translator_type.LENGTH} registers '
                               f'({translator_type.REGISTERS}), got {len(registers)}')
        wrong = [number for number, value in enumerate(registers)
                 if isinstance(value, bool) or not isinstance(value, int)
                 or not 0 <= value <= WORD]
        if wrong:
            number = wrong[0]
            return registers, (f'register {number} of the block is {registers[number]!r}, '
                               f'not a 16-bit word 0..65535 ({len(wrong)} such registers)')
        translator = translator_type(self._gateway, self._completion)
        try:
            return await translator.execute(registers)
        except Exception as error:  # noqa: BLE001 - every request gets an answer
            LOGGER.exception('PLC mailbox block (%s) failed unexpectedly', name)
            return translator.failed(registers, f'internal error: {type(error).__name__}: '
                                                f'{error}')
