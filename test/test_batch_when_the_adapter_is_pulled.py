"""A caller's batch to a drive, under way when the adapter is pulled, ends there.

It is answered at once, and nothing of it is sent once the adapter is back.

The gateway runs behind test/faulty_bus.py with one simulated drive (test_drive_bus_faults);
a batch of writes to the drive's profile velocity (0x6081), one distinct value each, runs
when the adapter is pulled. The accesses not sent by then must be answered as not sent, at
once, and never go out later: a write applied seconds later, after the bus came back, is one
the caller was told failed (or the robot has since moved on).
"""

import struct
import time

from test_drive_bus_faults import pull, pulled  # noqa: F401 (pulled: a fixture)
from test_drives import NODE

from cbcan_ros.msg import SdoAccess
from cbcan_ros.srv import SdoBatch

from conftest import SERVICE_TYPES, wait_until

SERVICE_TYPES.setdefault('sdo_batch', SdoBatch)

PROFILE_VELOCITY = 0x6081
ACCESSES = 1000
FIRST = 100000


def test_a_batch_under_way_when_the_adapter_is_pulled_is_answered_and_not_sent_later(
        pulled):  # noqa: F811
    axis, faults = pulled
    gateway = axis.gateway.node.gateway
    writes = [SdoAccess(node_id=NODE, index=PROFILE_VELOCITY, write=True,
                        data=list(struct.pack('<I', FIRST + number)))
              for number in range(ACCESSES)]
    batch = axis.gateway.call_async('sdo_batch', accesses=writes, timeout=30.0)

    def written() -> int:
        return struct.unpack('<I', axis.drive.value(PROFILE_VELOCITY, 0))[0] - FIRST
    wait_until(lambda: written() >= 5, 10.0, 'the batch under way')
    pull(faults)
    pulled_at = time.monotonic()
    wait_until(batch.done, 5.0, 'the batch answered after the pull')
    answered = time.monotonic() - pulled_at
    results = batch.result().results
    assert len(results) == ACCESSES
    succeeded = sum(result.success for result in results)
    assert succeeded < ACCESSES, 'the whole batch ran before the pull; make it longer'
    assert answered < 3.0, f'the batch was answered {answered:.1f} s after the pull'
    last = written()
    faults.clear()
    wait_until(lambda: gateway.bus.status.up and gateway.bus.status.reopen_count >= 1, 10.0,
               'the bus back')
    wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), 10.0,
               'the drive heard again once the adapter is back')
    sent = [m for m in faults.sent if m.arbitration_id == 0x600 + NODE
            and bytes(m.data[1:3]) == struct.pack('<H', PROFILE_VELOCITY)
            and m.data[0] & 0xE0 == 0x20]
    values = [struct.unpack('<I', bytes(m.data[4:8]))[0] - FIRST for m in sent]
    assert written() == last, (f'the drive took access {written()} of the batch after the bus '
                               f'came back (it had {last} at the pull); results: '
                               f'{succeeded} succeeded')
    assert len(values) <= succeeded + 1, f'accesses sent: {values[-10:]}'
