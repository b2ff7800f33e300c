"""A simulated device with a bootloader (CiA 302-3 program download), on durand.

:class:`BootloaderDevice` is a :class:`~.device.DurandDevice` that takes a new program:

- 0x1F50:1 (DOMAIN, write-only) stores the image as it arrives, by any SDO transfer durand
  serves (expedited, segmented, block with CRC);
- 0x1F51:1 (UNSIGNED8) is the control: 0 stops the program, 3 clears it (only when stopped),
  1 starts it (only a valid one), after which the device resets into it and sends its
  boot-up message. Reading it says 1 while the program runs, else 0;
- 0x1F56:1 (UNSIGNED32) identifies the program: the CRC-32 of the image, 0 without a valid
  one;
- 0x1F57:1 (UNSIGNED32) is the flash status: bit 0 while the flash is busy (``clear_time``
  after a clear, ``flash_time`` after an image arrived), then the error code in bits 1..7.

Faults to play, as constructor options: ``abort_at`` (the device aborts the download with
0x08000020 once that many bytes arrived), ``reset_at`` (the device resets, sending its
boot-up message, once that many bytes arrived; what follows of the image reaches the
restarted device), ``restarts_on_stop`` (seconds: the device restarts into its bootloader
when told to stop, as many do: right after its answer it hears and says nothing for that
long, then sends its boot-up message), ``flash_error`` (the code 0x1F57 reports after
flashing), ``comes_back`` False (the new program never sends anything: a device that does not
come back). The program and its state survive resets, as a bootloader's flash does.
"""

import time
from typing import Optional
import zlib

from durand.datatypes import DatatypeEnum as DT
from durand.object_dictionary import Record, Variable
from durand.services.sdo.server import SDODomainAbort

from .device import DurandDevice, WHOLE_DICTIONARY
from .scheduler import shared_scheduler

PROGRAM_DATA = 0x1F50
PROGRAM_CONTROL = 0x1F51
SOFTWARE_ID = 0x1F56
FLASH_STATUS = 0x1F57
PROGRAM = 1
STOP, START, CLEAR = 0, 1, 3
FLASH_BUSY = 0x01
NOT_CLEARED = 4  # 0x1F57 error code: flash not cleared before write
ABORT_NOT_STORED = 0x08000020
ABORT_DEVICE_STATE = 0x08000022
ABORT_INVALID_VALUE = 0x06090030
START_DELAY = 0.02  # s from the start command to the reset: its answer goes out first


class _ImageWriter:
    """Takes one download of 0x1F50:1 as durand hands it over (durand's download handler)."""

    def __init__(self, device: 'BootloaderDevice'):
        self._device = device

    def on_receive(self, data: bytes) -> None:
        device = self._device
        device.image += data
        if device.abort_at is not None and len(device.image) >= device.abort_at:
            raise RuntimeError('simulated fault: the flash takes no more')  # 0x08000020
        if device.reset_at is not None and len(device.image) >= device.reset_at:
            device.reset_at = None
            device.reset_now()

    def on_finish(self) -> None:
        self._device.flashed()

    def on_abort(self) -> None:
        """Keep the image as far as it came: the flash holds what was written."""


class BootloaderDevice(DurandDevice):
    """A durand device that takes program downloads (CiA 302-3) into program 1."""

    COMMANDS = (*DurandDevice.COMMANDS, PROGRAM_DATA, PROGRAM_CONTROL)

    def __init__(self, node_id: int, *args, image: bytes = b'firmware 1.0',
                 flash_time: float = 0.2, clear_time: float = 0.1,
                 abort_at: Optional[int] = None, reset_at: Optional[int] = None,
                 restarts_on_stop: Optional[float] = None, flash_error: int = 0,
                 comes_back: bool = True, **options):
        super().__init__(node_id, *args, **options)
        self.image = bytearray(image)
        self.program_running = True          # the program runs (0x1F51 reads 1)
        self.cleared = False         # cleared since the last image
        self.flash_time = flash_time
        self.clear_time = clear_time
        self.abort_at = abort_at
        self.reset_at = reset_at
        self.restarts_on_stop = restarts_on_stop
        self.flash_error = flash_error
        self.comes_back = comes_back
        self.starts = 0              # start commands taken
        self._error = 0              # 0x1F57 error code of the last flashing
        self._busy_until = 0.0

    @property
    def software_id(self) -> int:
        """Return what 0x1F56:1 reads: the image's CRC-32, 0 without a valid program."""
        return zlib.crc32(bytes(self.image)) if self._valid() else 0

    def flashed(self) -> None:
        """Flash the image that arrived whole: ``flash_time`` busy, then its error code."""
        self._error = self.flash_error or (0 if self.cleared else NOT_CLEARED)
        self.cleared = False
        self._busy_until = time.monotonic() + self.flash_time

    def _build_dictionary(self, od) -> None:
        super()._build_dictionary(od)
        for index, datatype, access, name in (
                (PROGRAM_DATA, DT.DOMAIN, 'wo', 'Program data'),
                (PROGRAM_CONTROL, DT.UNSIGNED8, 'rw', 'Program control'),
                (SOFTWARE_ID, DT.UNSIGNED32, 'ro', 'Program software identification'),
                (FLASH_STATUS, DT.UNSIGNED32, 'ro', 'Flash status identification')):
            record = Record(name=name)
            record[0] = Variable(DT.UNSIGNED8, 'const', 1, name='Highest sub-index supported')
            record[PROGRAM] = Variable(datatype, access, 0 if datatype != DT.DOMAIN else b'',
                                       name=f'{name} 1')
            od[index] = record
        od.set_read_callback(PROGRAM_CONTROL, PROGRAM, lambda: int(self.program_running))
        od.set_read_callback(SOFTWARE_ID, PROGRAM, lambda: self.software_id)
        od.set_read_callback(FLASH_STATUS, PROGRAM, self._flash_status)
        od.validate_callbacks[(PROGRAM_CONTROL, PROGRAM)].add(self._control)
        self.node.sdo_servers[0].download_manager.set_handler_callback(self._writer)

    def _writer(self, _node, index: int, subindex: int, _size) -> Optional[_ImageWriter]:
        if (index, subindex) != (PROGRAM_DATA, PROGRAM):
            return None  # durand stores any other object itself
        if self.program_running or self._busy():
            raise SDODomainAbort(ABORT_DEVICE_STATE, (index, subindex))
        self.image = bytearray()
        return _ImageWriter(self)

    def _control(self, command: int) -> None:
        """Carry out a write of 0x1F51:1; a refusal raises (durand answers its abort)."""
        where = (PROGRAM_CONTROL, PROGRAM)
        if command == STOP:
            if self.program_running and self.restarts_on_stop is not None:
                # Deaf from now on (the next command is lost in the restart), mute once the
                # answer is out.
                self._network.deaf = True
                shared_scheduler().add(0.0, self._restart_into_bootloader)
            self.program_running = False
        elif command == CLEAR:
            if self.program_running or self._busy():
                raise SDODomainAbort(ABORT_DEVICE_STATE, where)
            self.image = bytearray()
            self._error = 0
            self.cleared = True
            self._busy_until = time.monotonic() + self.clear_time
        elif command == START:
            if not self._valid():
                raise SDODomainAbort(ABORT_DEVICE_STATE, where)
            self.starts += 1
            shared_scheduler().add(START_DELAY, self._start_program)
        else:
            raise SDODomainAbort(ABORT_INVALID_VALUE, where)

    def _start_program(self) -> None:
        """Reset into the new program (a boot-up message), or fall silent for good."""
        if self._network is None:
            return  # stopped meanwhile
        self.program_running = True
        if not self.comes_back:
            self._network.muted = True  # the new program crashed before saying anything
            return
        self._boot(WHOLE_DICTIONARY, durand_reset=self.node.nmt.reset)

    def _restart_into_bootloader(self) -> None:
        """Go silent (deaf since the stop) for ``restarts_on_stop`` s, then send the boot-up."""
        network = self._network
        if network is None:
            return  # stopped meanwhile
        network.muted = True

        def back() -> None:
            if self._network is network:
                network.muted = network.deaf = False
                self.reset_now()
        shared_scheduler().add(self.restarts_on_stop, back)

    def reset_now(self) -> None:
        """Reset as a power glitch or watchdog does: the boot-up message, the program gone."""
        self.program_running = False
        self._boot(WHOLE_DICTIONARY, durand_reset=self.node.nmt.reset)

    def _flash_status(self) -> int:
        return FLASH_BUSY if self._busy() else self._error << 1

    def _valid(self) -> bool:
        return bool(self.image) and not self._error and not self._busy() and not self.cleared

    def _busy(self) -> bool:
        return time.monotonic() < self._busy_until
