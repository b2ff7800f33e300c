"""A finished request frees what it held at once, not when its timeout would have run out."""

import gc
import struct
import threading
import weakref

from cbcan_ros.core.gateway import Gateway, GatewayConfig
from cbcan_ros.core.sdo.request_queue import Deadlines
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import new_channel, wait_until

NODE = 7
LONG_TIMEOUT = 60.0


def test_answered_requests_with_a_long_timeout_are_not_kept():
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel)
    device.start()
    gateway = Gateway(GatewayConfig(channel=channel))
    gateway.start()
    try:
        futures = [gateway.sdo_read(NODE, 0x1000, 0, timeout=LONG_TIMEOUT) for _ in range(50)]
        for future in futures:
            assert future.result(LONG_TIMEOUT).data == struct.pack('<I', 0x00020192)
        kept = [weakref.ref(future) for future in futures]
        del futures, future
        gc.collect()
        alive = sum(ref() is not None for ref in kept)
        assert alive == 0, f'{alive} of {len(kept)} answered requests are still referenced'
    finally:
        gateway.stop()
        device.stop()


def test_cancelled_deadline_watches_are_dropped_and_never_fire():
    deadlines = Deadlines()
    fired = []
    try:
        for number in range(10_000):
            watch = deadlines.watch(1e9, lambda n=number: fired.append(n))
            deadlines.cancel(watch)
        assert len(deadlines) < 2 * Deadlines.COMPACT_AT
        due = threading.Event()
        deadlines.cancel(deadlines.watch(0.0, lambda: fired.append('cancelled')))
        deadlines.watch(0.0, due.set)
        wait_until(due.is_set, 10.0, 'a watch that is due to fire')
        assert fired == []
    finally:
        deadlines.stop()
