"""Soak: 20,000 mixed requests to the installed node, with flat memory in the node process.

Every request has a 60 s timeout: what a request holds must be freed when it is answered,
not when its timeout would have run out.

The node runs as a robot runs it (a separate process, its simulated devices on its own virtual
bus); this process is the client, so both sides have a core of their own.
"""

import struct
import uuid

from cbcan_ros.srv import SdoRead, SdoWrite

from conftest import HEAVY, wait_for_future
from node_process import service_client

pytestmark = HEAVY

TOTAL = 20_000
BURST = 150
WARM_UP = 2_000
ALLOWED_GROWTH_KB = 15_000  # a leak of 1 KB per request would be 18 MB over the run
TIMEOUT = 60.0
DEVICE_TYPE = struct.pack('<I', 0x00020192)


def rss_kb(pid: int) -> int:
    with open(f'/proc/{pid}/status') as status:
        line = next(line for line in status if line.startswith('VmRSS:'))
    return int(line.split()[1])


def test_twenty_thousand_mixed_requests_keep_the_node_s_memory_flat(start_node, client_node,
                                                                   measured):
    name = f'/soak{uuid.uuid4().hex[:8]}/cbcan'
    gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                          '-p', f'can.channel:=soak{uuid.uuid4().hex[:8]}',
                          '-p', 'simulation.devices:=[2, 3, 5]'])
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    sdo_write = service_client(client_node, SdoWrite, f'{name}/sdo_write', gateway)

    def request(i):
        node = (2, 3, 5)[i % 3]
        kind = i % 10
        if kind < 5:
            return (sdo_read, SdoRead.Request(node_id=node, index=0x1000, timeout=TIMEOUT),
                    DEVICE_TYPE)
        if kind < 8:
            data = list(struct.pack('<H', i & 0xFFFF))
            return sdo_write, SdoWrite.Request(node_id=node, index=0x2001, data=data,
                                                    timeout=TIMEOUT), None
        if kind == 8:
            return (sdo_read, SdoRead.Request(node_id=node, index=0x6000, timeout=TIMEOUT),
                    0x06020000)
        return sdo_read, SdoRead.Request(node_id=0, index=0x1018, subindex=2,
                                           timeout=TIMEOUT), (
            struct.pack('<I', 0xCBCA))

    def run(first, count):
        for start in range(first, first + count, BURST):
            sent = []
            for i in range(start, min(start + BURST, first + count)):
                client, message, expected = request(i)
                sent.append((i, client.call_async(message), expected))
            for i, future, expected in sent:
                answer = wait_for_future(future, 30.0)
                if isinstance(expected, bytes):
                    assert answer.success and bytes(answer.data) == expected, (i, answer)
                elif expected is None:
                    assert answer.success, (i, answer.message)
                else:
                    assert answer.abort_code == expected, (i, answer.message)

    run(0, WARM_UP)
    before = rss_kb(gateway.process.pid)
    run(WARM_UP, TOTAL - WARM_UP)
    after = rss_kb(gateway.process.pid)
    measured(f'cbcan_node RSS before {before} kB, after {after} kB, growth {after - before} kB '
             f'over {TOTAL - WARM_UP} requests with a {TIMEOUT:g} s timeout')
    assert after - before < ALLOWED_GROWTH_KB
