"""The deadline watches of queued requests: each fires once, at its time, while others go.

Requests answered in time cancel their watch, and cancelled watches are compacted away while
the deadline thread is firing others; none may be lost, fire twice, or stay held.
"""

import random
import threading
import time

from cbcan_ros.core.sdo.request_queue import Deadlines

from conftest import wait_until

WATCHES = 20_000
SPREAD = 0.5  # seconds over which the deadlines fall


def test_watches_fire_once_each_while_others_are_cancelled_and_compacted():
    deadlines = Deadlines()
    lock = threading.Lock()
    fired = {}
    cancelled = set()
    late = []

    def expire(number, due):
        now = time.monotonic()
        with lock:
            fired[number] = fired.get(number, 0) + 1
            if now < due:
                late.append((number, due - now))

    try:
        start = time.monotonic()
        entries = []
        for number in range(WATCHES):
            due = start + random.uniform(0.0, SPREAD)
            entries.append(deadlines.watch(due, lambda n=number, d=due: expire(n, d)))
        order = list(range(WATCHES))
        random.shuffle(order)
        for number in order[:WATCHES // 2]:  # cancelled while others are firing
            with lock:
                if number in fired:
                    continue
                cancelled.add(number)
            deadlines.cancel(entries[number])
        def settled():
            with lock:
                return len(fired.keys() | cancelled) >= WATCHES
        wait_until(settled, 30.0, 'every watch fired or cancelled')
        with lock:
            twice = [number for number, count in fired.items() if count != 1]
            live = set(range(WATCHES)) - cancelled
            missing = live - set(fired)
        assert not twice, f'{len(twice)} watches fired more than once'
        assert not missing, f'{len(missing)} watches never fired'
        assert not late, f'{len(late)} watches fired before their time: {late[:3]}'
        assert len(deadlines) <= 2 * Deadlines.COMPACT_AT, len(deadlines)
    finally:
        deadlines.stop()


def test_a_deadline_past_what_a_thread_can_wait_or_an_expiry_that_fails_stops_no_other():
    # One deadline thread times out every queued request of the gateway: a watch 1e10 s
    # away (past threading.TIMEOUT_MAX) ended it with OverflowError, and so would an
    # expiry that raised; every later request then waited past its timeout.
    deadlines = Deadlines()
    fired = threading.Event()

    def fail():
        raise RuntimeError('an expiry that fails')
    try:
        deadlines.watch(time.monotonic() + 1e10, lambda: None)
        deadlines.watch(time.monotonic() + 0.01, fail)
        deadlines.watch(time.monotonic() + 0.05, fired.set)
        assert fired.wait(5.0), 'the deadline after them never fired'
    finally:
        deadlines.stop()
