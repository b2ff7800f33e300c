"""How a gateway's services are called from Python, whatever thread or executor calls.

A :class:`ServiceCaller` has a node of its own, spun by a thread of its own, so a blocking
call works whether or not the caller's node is spun by an executor, and also inside one of
its callbacks; the awaitable form resumes on the caller's node's executor. Each call is
written once, as a generator method of steps that yields the futures it waits for;
:func:`blocking` and :func:`awaitable` turn it into the two methods callers use.
"""

from concurrent.futures import Future as ThreadFuture
import functools
import threading
import time
from typing import Optional
import uuid

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future as RosFuture

from .service_qos import SERVICE_QOS

# Seconds an answer may take beyond the SDO timeout of the request (a segmented transfer of
# a large object takes many SDO round trips, each with its own timeout).
ANSWER_MARGIN = 30.0
# How often the client's thread looks at deadlines and newly found services while calls
# wait and nothing else wakes it.
POLL = 0.1


class GatewayError(Exception):
    """A call to the gateway did not succeed."""


class GatewayUnavailable(GatewayError):
    """No gateway answers: it is not running, not discovered, or did not reply in time."""


def _nothing(*_arguments) -> None:
    """Do nothing: a callback that is there to wake an executor when it is scheduled."""


def _named(method, steps, suffix: str = ''):
    """Give ``method`` the documentation of ``steps`` and its name without the underscore."""
    functools.update_wrapper(method, steps)
    method.__name__ = steps.__name__.lstrip('_') + suffix
    method.__qualname__ = steps.__qualname__.replace(steps.__name__, method.__name__)
    return method


def blocking(steps):
    """Return the blocking method that runs the generator method ``steps``."""
    def method(self, *args, **kwargs):
        return self._block(steps(self, *args, **kwargs))
    return _named(method, steps)


def awaitable(steps):
    """Return the ``async`` method that runs the generator method ``steps``."""
    async def method(self, *args, **kwargs):
        return await self._await(steps(self, *args, **kwargs))
    return _named(method, steps, '_async')


class ServiceCaller:
    """Calls to the services of one gateway (e.g. ``/can0/cbcan``), on behalf of ``node``.

    ``wait``: seconds to wait for the gateway's services to be found. Call :meth:`close`
    when done (or use the caller as a context manager).
    """

    def __init__(self, node: Node, gateway: str, wait: float):
        name = gateway.strip().rstrip('/')
        self.gateway = name if name.startswith('/') else f'/{name}'
        self.wait = wait
        self._node = node
        self._own = Node(f'{node.get_name()}_gateway_client_{uuid.uuid4().hex[:8]}',
                         namespace=node.get_namespace(), context=node.context,
                         start_parameter_services=False, enable_rosout=False)
        self._clients = {}
        self._lock = threading.Lock()
        # (condition, its future, deadline): looked at by the thread after each spin.
        self._watches = []
        self._stopped = False  # the thread ends, or has ended
        self._closed = False
        self._wake = self._own.create_guard_condition(_nothing)
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(self._own)
        self._spinner = threading.Thread(target=self._spin, daemon=True,
                                         name=f'gateway client {self.gateway}')
        self._spinner.start()

    def __enter__(self) -> 'ServiceCaller':
        return self

    def __exit__(self, *_exception) -> None:
        self.close()

    def close(self) -> None:
        """Stop the client's thread and destroy its node; waiting calls fail at once."""
        with self._lock:
            if self._closed:
                return
            self._closed = self._stopped = True
        if self._spinner.is_alive():
            self._wake.trigger()
            self._spinner.join()
        self._executor.shutdown(timeout_sec=1.0)
        self._own.destroy_node()

    # --- the thread that spins the client's own node

    def _spin(self) -> None:
        reason = 'the client is closed'
        try:
            while not self._stopped:
                # Deadlines need looking at; without any, only an event (an answer, a new
                # call, close) can change something, and each wakes the executor.
                self._executor.spin_once(timeout_sec=POLL if self._watches else None)
                self._settle(time.monotonic())
        except Exception as error:  # rclpy shut down under the client: fail every caller
            reason = f'the client stopped: {error!r}'
        with self._lock:
            self._stopped = True
            watches, self._watches = self._watches, []
        for _condition, future, _deadline in watches:
            future.set_exception(GatewayUnavailable(reason))

    def _settle(self, now: float) -> None:
        finished = []
        with self._lock:
            waiting = []
            for condition, future, deadline in self._watches:
                holds = bool(condition())
                if holds or now >= deadline:
                    finished.append((future, holds))
                else:
                    waiting.append((condition, future, deadline))
            self._watches = waiting
        for future, holds in finished:
            future.set_result(holds)

    def _when(self, condition, timeout: float) -> ThreadFuture:
        """Return a future: True once ``condition()`` holds, False after ``timeout`` s.

        Futures of rclpy are not waited on directly: with several threads calling while
        another spins, about 1 in 30 completed without running its done-callback.
        """
        future = ThreadFuture()
        if condition():
            future.set_result(True)
            return future
        with self._lock:
            if self._stopped:
                future.set_exception(GatewayUnavailable('the client is closed'))
                return future
            self._watches.append((condition, future, time.monotonic() + timeout))
        self._wake.trigger()
        return future

    def _block(self, steps):
        """Run a generator of steps, waiting for each future it yields in this thread."""
        outcome = None
        try:
            while True:
                outcome = steps.send(outcome).result()
        except StopIteration as done:
            return done.value

    async def _await(self, steps):
        """Run a generator of steps, awaiting each future it yields on ``node``'s executor."""
        outcome = None
        try:
            while True:
                waited = steps.send(outcome)
                # set_result schedules the waiter's done-callback on the executor, which
                # wakes it to resume this coroutine; nothing else would wake it.
                waiter = RosFuture(executor=self._node.executor)
                waiter.add_done_callback(_nothing)
                waited.add_done_callback(functools.partial(_hand_over, waiter))
                outcome = await waiter
        except StopIteration as done:
            return done.value

    # --- one exchange with a service; the typed calls of a client are built on it

    def _client(self, service_type, service: str):
        with self._lock:
            if service not in self._clients:
                self._clients[service] = self._own.create_client(
                    service_type, f'{self.gateway}/{service}', qos_profile=SERVICE_QOS)
            return self._clients[service]

    def _call(self, service_type, service: str, request,
                  answer_within: Optional[float] = None):
        """Call ``gateway/service`` and return the response, whatever it says."""
        client = self._client(service_type, service)
        if not (yield self._when(client.service_is_ready, self.wait)):
            raise GatewayUnavailable(
                f'no gateway at {self.gateway}: is cbcan_node running? (waited '
                f'{self.wait:g} s for {service}; check the gateway name and ROS_DOMAIN_ID)')
        within = answer_within or self.wait + ANSWER_MARGIN
        future = client.call_async(request)
        if not (yield self._when(future.done, within)):
            future.cancel()
            raise GatewayUnavailable(f'{self.gateway}/{service} did not answer within '
                                     f'{within:g} s')
        return future.result()

    call = blocking(_call)
    call_async = awaitable(_call)


def _hand_over(waiter: RosFuture, waited: ThreadFuture) -> None:
    if waited.exception() is not None:
        waiter.set_exception(waited.exception())
    else:
        waiter.set_result(waited.result())

