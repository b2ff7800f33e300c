"""The gateway node (``cbcan_node``), and how both gateway nodes run and shut down.

The node's services and topics are :class:`~.interface.GatewayInterface`; the managed
variant (``lifecycle_node.py``) makes the same interface in its configure transition.

Shutdown (SIGINT, SIGTERM or ``destroy_node``) answers every waiting call before rclpy goes
away: ROS can only deliver an answer while the node still exists.
"""

import contextlib
import ctypes
import logging
import os
import select
import signal
import sys
import threading
import time
from typing import Callable, List, NoReturn

import rclpy
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .answer_retry import retry_the_node_services
from .config import NodeParameters
from .goals import KeptActionServer
from .interface import ANSWER_GRACE, GatewayInterface
from .rclpy_gaps import end_spin_once

# The longest an idle executor sleeps before it looks whether shutdown began (it is woken
# at once anyway, ``end_spin_once``; this only bounds a missed wake-up).
SPIN_CHECK = 1.0

# How long shutdown waits for a spin in progress to end; a backlog of requests, each
# answered "shutting down" at once, took about a second under load.
SPIN_STOP = 5.0

# The longest a shutdown may take from the first signal (docs/services.md, Shutdown). Its steps
# wait for threads with timeouts of their own (SPIN_STOP, ANSWER_GRACE, the bus and device
# threads), which add up to about this much only when several hang at once; a step that
# hangs without a timeout (a driver stuck in a system call) must not keep the process alive.
SHUTDOWN_LIMIT = 10.0
SHUTDOWN_OVERRUN = 1  # the exit status when shutdown did not finish within SHUTDOWN_LIMIT

# Failures of the executor in a row after which the node gives up (exit status 1) rather
# than spin in a loop of errors.
EXECUTOR_FAILURES = 100

# Requests and events the executor had queued for services and topics that a managed node's
# transition has just destroyed fail as it takes them (InvalidHandle): thousands under a
# burst of calls at cleanup. Counted, not failures, and logged at most once in this long.
GONE_LOG_PERIOD = 10.0


def make_executor():
    """Return the executor the gateway nodes spin on.

    rclpy's EventsExecutor dispatches each request straight to its callback, which hands it
    to the gateway; the default executor rebuilds its wait set on every pass, which measured
    here as most of a call's time and a third of a burst's throughput (``make bench``). Its
    ``spin_once(timeout)`` is used rather than ``spin()``, which was reported to busy-wait.
    """
    return EventsExecutor()


class CbcanNode(Node):
    """One CAN bus as ROS 2 services and a node-state topic, active from the start."""

    def __init__(self, **kwargs):
        super().__init__('cbcan', **kwargs)
        self._destroyed = False
        self._answers = retry_the_node_services(self)
        self.interface = GatewayInterface(self, NodeParameters(self))

    @property
    def gateway(self):
        """The CANopen core this node maps."""
        return self.interface.gateway

    def shut_down_gateway(self) -> None:
        """Answer every waiting call ("shutting down"), abort running transfers, close the bus."""
        self.interface.shut_down()

    def destroy_node(self) -> None:
        """Answer waiting calls, close the bus, stop the simulated devices (once)."""
        if self._destroyed:
            return
        self._destroyed = True
        self.interface.destroy()
        KeptActionServer.destroy_all(self)
        self._answers.close()
        super().destroy_node()


def run(make_node: Callable[[], Node], program: str, args=None) -> int:
    """Spin the node ``make_node`` returns until SIGINT or SIGTERM; a second signal ends it.

    The node must have ``shut_down_gateway()``, called before the executor stops, so every
    waiting call is answered while ROS can still deliver it. The process ends within
    ``SHUTDOWN_LIMIT`` of the signal; a shutdown that finished ends it at once (``_leave``),
    so this returns only when the node could not start: call it as a program's last act.
    """
    # The handler runs in the main thread between any two of its bytecodes, so it takes no
    # lock: setting an Event there once deadlocked a node whose main thread was inside that
    # Event's wait, holding its lock (a fresh-clone run; the node never began shutting down).
    signalled: List[int] = []

    def on_signal(signum, _frame) -> None:
        if signalled:
            os._exit(128 + signum)  # the impatient second Ctrl-C: no cleanup, no traceback
        signalled.append(signum)

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    # Whichever thread the kernel hands a signal to, Python writes its number here, which
    # wakes the main thread waiting on this pipe to run the handler.
    wake_read, wake_write = os.pipe()
    os.set_blocking(wake_read, False)
    os.set_blocking(wake_write, False)
    signal.set_wakeup_fd(wake_write, warn_on_full_buffer=False)
    # rclpy's own handler would shut the context down first, and a node without a context
    # can answer nobody: shutdown is ours, in order.
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = make_node()
    except Exception as error:  # noqa: BLE001 - a configuration error ends the process cleanly
        print(f'{program}: cannot start: {error}', file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = make_executor()
    executor.add_node(node)

    spinning = threading.Event()
    spinning.set()
    broken = []
    ended = threading.Event()  # the executor's thread ended (the main thread only reads it)

    def spin() -> None:
        failures, gone, gone_logged = 0, 0, None
        try:
            while spinning.is_set():
                try:
                    executor.spin_once(timeout_sec=SPIN_CHECK)
                    failures = 0
                except ExternalShutdownException:
                    return
                except InvalidHandle:  # not a failure: see GONE_LOG_PERIOD
                    gone += 1
                    now = time.monotonic()
                    if gone_logged is None or now - gone_logged >= GONE_LOG_PERIOD:
                        said = f'{gone} requests or events' if gone > 1 else 'a request or event'
                        node.get_logger().warning(
                            f'{said} for services or topics just taken away (cleanup, shutdown) '
                            f'dropped: nothing is left to serve them (more are counted and '
                            f'logged at most every {GONE_LOG_PERIOD:g} s)')
                        gone, gone_logged = 0, now
                except Exception as error:  # noqa: BLE001 - a bad callback must not end it
                    failures += 1
                    if failures == 1:
                        node.get_logger().error(f'a callback failed, serving goes on: {error!r}')
                    if failures >= EXECUTOR_FAILURES:
                        broken.append(error)
                        node.get_logger().fatal(f'the executor keeps failing: {error!r}')
                        return
        finally:
            ended.set()
            with contextlib.suppress(BlockingIOError):
                os.write(wake_write, b'\0')

    spinner = threading.Thread(target=spin, name='executor', daemon=True)
    spinner.start()
    while not (signalled or ended.is_set()):  # the main thread only waits
        select.select([wake_read], [], [], SPIN_CHECK)
        with contextlib.suppress(BlockingIOError):
            os.read(wake_read, 512)
    node.get_logger().info('shutting down: answering waiting calls')
    overrun = threading.Timer(SHUTDOWN_LIMIT, give_up_shutdown, (node, program))
    overrun.daemon = True
    overrun.start()
    node.shut_down_gateway()
    # Executor.shutdown() does not wait for a spin in progress and destroys what that spin
    # uses (rclpy 7.1.6): end the spinning first (the gateway is stopped, so whatever it
    # still takes is answered at once), then shut the executor down. Requests it never took
    # are answered when the services go (GatewayInterface.destroy).
    spinning.clear()
    end_spin_once(node)
    spinner.join(SPIN_STOP)
    executor.shutdown(timeout_sec=ANSWER_GRACE)
    node.destroy_node()
    rclpy.try_shutdown()
    # Everything is answered, stopped and closed. The process leaves now, without the
    # interpreter's finalization and the native libraries' exit handlers: a node that had
    # logged the end of its shutdown stayed for good now and then (twice in some twenty
    # suite runs), past the limit timer too, which finalization had already stopped.
    _leave(1 if broken else 0)


def _leave(status: int) -> NoReturn:
    """End the process with ``status`` at once, its output written out first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).fflush(None)  # C stdio buffers (rcutils' console output)
    os._exit(status)


def give_up_shutdown(node: Node, program: str) -> None:
    """End the process that did not finish shutting down within ``SHUTDOWN_LIMIT``."""
    message = (f'{program}: shutdown did not end the process within {SHUTDOWN_LIMIT:.0f} s; '
               f'exiting without waiting further')
    try:
        node.get_logger().error(message)
    except Exception:  # noqa: BLE001 - rclpy may be half gone: say it on stderr instead
        print(message, file=sys.stderr, flush=True)
    os._exit(SHUTDOWN_OVERRUN)


def main(args=None) -> int:
    """Run the gateway node until SIGINT or SIGTERM; a second signal ends it at once."""
    return run(CbcanNode, 'cbcan_node', args)
