"""A node's exit does not wait out its executor's idle spin (rclpy gap 9, ``end_spin_once``).

``cbcan_node`` spins rclpy's ``EventsExecutor`` with ``spin_once(timeout)`` and stops that
loop at shutdown. ``EventsExecutor.wake()`` leaves a ``spin_once`` waiting for work until its
timeout, so every exit of the node waited up to a second (the suite's tests stop hundreds of
nodes). The timeout here is a minute: a spin that is not ended at once fails the join.
"""

import threading

import rclpy
from rclpy.experimental import EventsExecutor

from cbcan_ros.ros.rclpy_gaps import end_spin_once

IDLE_SPIN = 60.0  # s: the spin_once a wake must end
JOINED = 30.0  # s: far beyond a wake, far below IDLE_SPIN


def test_end_spin_once_ends_an_idle_spin_of_the_events_executor(ros_context):
    node = rclpy.create_node('spin_ender')
    executor = EventsExecutor()
    executor.add_node(node)
    spun = threading.Event()

    def spin() -> None:
        executor.spin_once(timeout_sec=IDLE_SPIN)
        spun.set()
    spinner = threading.Thread(target=spin, daemon=True)
    try:
        spinner.start()
        end_spin_once(node)
        assert spun.wait(JOINED), f'spin_once still waiting after {JOINED:g} s'
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
