"""A drive's commanded values that its first read missed are read again, and its RPDOs used.

An RPDO frame carries every object it maps: the gateway fills those it commands with its
last value, read from the drive when it is first heard. An object that read missed (the
drive's answer timed out on a busy bus) left every RPDO mapping it unused for good, since a
frame would carry a value of the gateway's making: every controlword went by SDO. Now the
values missed are read again with the objects the RPDOs hold, at once and then at each poll
until they are in, and the frames go out as mapped.
"""

import struct

from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos

from conftest import Harness, new_channel, wait_until

NODE = 7
CSV = 9
WAIT = 15.0  # seconds: a ceiling for what takes a fraction of a second on a quiet machine
TARGET_POSITION_UPLOAD = b'\x40\x7a\x60\x00'  # initiate upload of 0x607A:0
CONTROLWORD_DOWNLOAD = b'\x2b\x40\x60\x00'  # expedited download of 2 bytes to 0x6040:0
GENERAL_ERROR = 0x08000000


class DriveMissingItsTargetAtFirst(DurandDrive):
    """A drive whose first read of its target position (0x607A) fails with an abort."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.target_reads = 0

    def _on_sdo_frame(self, durand_handler, cob_id: int, data: bytes) -> None:
        if bytes(data[:4]) == TARGET_POSITION_UPLOAD:
            self.target_reads += 1
            if self.target_reads == 1:
                self._network.send(0x580 + self.node_id, struct.pack(
                    '<BHBI', 0x80, 0x607A, 0, GENERAL_ERROR))
                return
        super()._on_sdo_frame(durand_handler, cob_id, data)


def test_a_target_the_first_read_missed_is_read_again_and_the_enable_goes_by_rpdo(
        start_durand):
    channel = new_channel()
    drive = start_durand(NODE, kind=DriveMissingItsTargetAtFirst, channel=channel,
                         pdos=default_drive_pdos())  # RPDO 1: controlword, target, mode
    wait_until(lambda: drive.running, WAIT, 'the drive receiving')
    gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                       'drives.nodes': [NODE], 'drives.command_timeout': 0.0,
                       'drives.consumer_time': 3.0})
    bus = gateway.raw_bus()
    try:
        assert gateway.call('nmt_command', node_id=NODE, command=1).success
        wait_until(lambda: drive.target_reads >= 2, WAIT, 'the target position read again')
        drives = gateway.node.gateway.drives
        wait_until(lambda: drives.status(NODE).state != 'UNKNOWN', WAIT, 'the drive read')
        while bus.recv(0) is not None:  # the frames before the enable
            pass
        answer = gateway.call('drive_command', node_id=NODE, command='enable', mode=CSV)
        assert answer.success, answer.message
        # The virtual bus holds each frame from the moment it was sent.
        frames = list(iter(lambda: bus.recv(0), None))
        by_sdo = [m for m in frames if m.arbitration_id == 0x600 + NODE
                  and bytes(m.data[:4]) == CONTROLWORD_DOWNLOAD]
        in_rpdo = [m for m in frames if m.arbitration_id == 0x200 + NODE]
        assert not by_sdo and in_rpdo, (
            f'controlwords by SDO: {[bytes(m.data).hex() for m in by_sdo]}; '
            f'RPDO 1 frames: {[bytes(m.data).hex() for m in in_rpdo]}')
    finally:
        bus.shutdown()
        gateway.close()
