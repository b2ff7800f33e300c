"""Calling a gateway from Python: the one client of its services, for scripts and nodes.

::

    gateway = GatewayClient(node, '/can0/cbcan')
    gateway.read(5, 0x1000, type='u32')                       # blocking: in scripts
    value = await gateway.read_async(5, 0x1000, type='u32')   # in an async callback

Every call goes through a node of the client's own, spun by a thread of its own
(``service_caller``), so a blocking call works whether or not ``node`` is spun by an
executor, and also inside one of ``node``'s callbacks. The awaitable forms resume on
``node``'s executor (a ``SingleThreadedExecutor`` or ``MultiThreadedExecutor``; rclpy's
``EventsExecutor`` does not run ``async`` callbacks). The services are called with the
gateway's own ``SERVICE_QOS``: ROS's default depth of 10 loses answers of a burst of calls.

Errors: when the gateway answers ``success: false`` the call raises :class:`RequestFailed`
(its ``abort_code``, ``message`` and the whole ``response``); when no gateway answers, or not
in time, :class:`GatewayUnavailable`. A value that does not fit its type raises ValueError.
:meth:`GatewayClient.batch` raises neither for a failed access: it answers every access.
"""

from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Sequence, Union

from rclpy.node import Node

from ..action import ProgramDownload
from ..core.boot.service import DEFAULT_CALL_TIMEOUT
from ..core.sdo.requests import MAX_TIMEOUT
from ..core.values import check_type, decode_value, encode, Value
from ..msg import BootStates, NodeStates, SdoAccess
from ..srv import Boot, NmtCommand, NmtState, SdoBatch, SdoRead, SdoWrite
from .boot import BOOT_STATES_QOS
from .interface import NODE_STATES_QOS
from .rclpy_gaps import FeedbackFirstActionClient
from .service_caller import (
    ANSWER_MARGIN,
    awaitable,
    blocking,
    GatewayError,
    GatewayUnavailable,
    ServiceCaller,
)

DEFAULT_GATEWAY = '/can0/cbcan'
DEFAULT_WAIT = 5.0
# Seconds between looks at whether the gateway is still there while an action's goal runs.
PRESENCE_CHECK = 1.0

NMT_COMMANDS = {
    'start': NmtCommand.Request.START,
    'stop': NmtCommand.Request.STOP,
    'preop': NmtCommand.Request.ENTER_PRE_OPERATIONAL,
    'reset': NmtCommand.Request.RESET_NODE,
    'reset-comm': NmtCommand.Request.RESET_COMMUNICATION,
}


class RequestFailed(GatewayError):
    """The gateway answered ``success: false``: a device's abort, a refused request.

    ``abort_code`` (0 when the answer has none), ``message``, ``response``; ``detail`` is
    the message with its abort code; ``what`` the request (``read node 5 object 0x6000:00``).
    """

    def __init__(self, what: str, response):
        self.what = what
        self.response = response
        self.abort_code = getattr(response, 'abort_code', 0)
        self.message = response.message
        self.detail = describe(response)
        super().__init__(f'{what}: {self.detail}')


def describe(response) -> str:
    """Return what an answer with ``success: false`` says: its message, with its abort code."""
    abort_code = getattr(response, 'abort_code', 0)
    code = f'0x{abort_code:08X}'
    # The gateway's message names the code already ("0x06020000 NOT_EXIST: ...").
    return f'{code}: {response.message}' if abort_code and code not in response.message else (
        response.message)


@dataclass(frozen=True)
class Read:
    """A read of a batch; its result's ``value`` is decoded as ``type``."""

    node_id: int
    index: int
    subindex: int = 0
    type: str = 'hex'
    max_size: int = 0

    def __post_init__(self):
        check_type(self.type)

    def access(self) -> SdoAccess:
        """Return the access as the service takes it."""
        return SdoAccess(node_id=self.node_id, index=self.index, subindex=self.subindex,
                         max_size=self.max_size)


@dataclass(frozen=True)
class Write:
    """A write of a batch: ``value`` as ``type`` (bytes, or hex text, for ``hex``)."""

    node_id: int
    index: int
    subindex: int
    value: Value
    type: str = 'hex'

    def access(self) -> SdoAccess:
        """Return the access as the service takes it; ValueError if the value does not fit."""
        what = f'write {_object(self.node_id, self.index, self.subindex)}'
        return SdoAccess(node_id=self.node_id, index=self.index, subindex=self.subindex,
                         write=True, data=list(_encoded(self.value, self.type, what)))


class Result(NamedTuple):
    """The answer to one access of a batch.

    ``value``: for a successful read, its bytes decoded as the read's type; else None. An
    answer that does not fit the type is a failure whose message says so (abort code 0).
    """

    success: bool
    abort_code: int
    message: str
    data: bytes
    value: Optional[Value]


def answer_within(timeout: float) -> float:
    """Return how long to wait for the answer to a request with SDO ``timeout`` (0: default)."""
    return (timeout or MAX_TIMEOUT) + ANSWER_MARGIN


def _object(node_id: int, index: int, subindex: int) -> str:
    return f'node {node_id} object 0x{index:04X}:{subindex:02X}'


def _encoded(value: Value, value_type: str, what: str) -> bytes:
    try:
        return encode(value, value_type)
    except ValueError as error:
        raise ValueError(f'{what}: {error}') from None


def _decoded(data: bytes, value_type: str, what: str) -> Value:
    try:
        return decode_value(data, value_type)
    except ValueError as error:
        raise ValueError(f'{what}: {error}') from None


class GatewayClient(ServiceCaller):
    """The services and node states of one gateway (``/can0/cbcan``), called from ``node``.

    ``wait``: seconds to wait for the gateway's services to be found. Call :meth:`close`
    when done (or use the client as a context manager).
    """

    def __init__(self, node: Node, gateway: str = DEFAULT_GATEWAY, wait: float = DEFAULT_WAIT):
        super().__init__(node, gateway, wait)
        self._latest: Dict[str, List] = {}  # topic: the messages kept (the newest last)
        self._downloads: Optional[FeedbackFirstActionClient] = None

    def subscribe_states(self, callback):
        """Call ``callback(NodeStates)`` on ``node``'s executor for every state change.

        The latest message arrives at once (the topic is latched); returns the subscription.
        """
        return self._node.create_subscription(NodeStates, f'{self.gateway}/node_states',
                                              callback, NODE_STATES_QOS)

    def _read(self, node_id: int, index: int, subindex: int = 0, type: str = 'hex',
              timeout: float = 0.0, max_size: int = 0):
        """Read an object and return its value as ``type`` (``hex``: the bytes).

        ``timeout``: seconds for the SDO, 0 = the gateway's ``sdo.timeout``.
        """
        check_type(type)
        response = yield from self._call(SdoRead, 'sdo_read', SdoRead.Request(
            node_id=node_id, index=index, subindex=subindex, max_size=max_size,
            timeout=float(timeout)), answer_within(timeout))
        what = f'read {_object(node_id, index, subindex)}'
        if not response.success:
            raise RequestFailed(what, response)
        return _decoded(bytes(response.data), type, what)

    read = blocking(_read)
    read_async = awaitable(_read)

    def _write(self, node_id: int, index: int, subindex: int, value: Value, type: str = 'hex',
               timeout: float = 0.0):
        """Write ``value`` as ``type`` to an object (``hex``: bytes, or hex text)."""
        what = f'write {_object(node_id, index, subindex)}'
        data = _encoded(value, type, what)
        response = yield from self._call(SdoWrite, 'sdo_write', SdoWrite.Request(
            node_id=node_id, index=index, subindex=subindex, data=list(data),
            timeout=float(timeout)), answer_within(timeout))
        if not response.success:
            raise RequestFailed(what, response)

    write = blocking(_write)
    write_async = awaitable(_write)

    def _batch(self, accesses: Sequence[Union[Read, Write, SdoAccess]],
               timeout: float = 0.0):
        """Run reads and writes in one call; return one :class:`Result` per access, in order.

        Accesses to one device run in the order given, devices in parallel; a failed access
        does not stop the others. ``timeout``: seconds for the whole batch.
        """
        messages = [item if isinstance(item, SdoAccess) else item.access()
                    for item in accesses]
        response = yield from self._call(SdoBatch, 'sdo_batch', SdoBatch.Request(
            accesses=messages, timeout=float(timeout)), answer_within(timeout))
        results = []
        for item, answer in zip(accesses, response.results, strict=True):
            data = bytes(answer.data)
            result = Result(answer.success, answer.abort_code, answer.message, data, None)
            if answer.success and isinstance(item, Read):
                try:
                    result = result._replace(value=decode_value(data, item.type))
                except ValueError as error:
                    result = result._replace(success=False, message=str(error))
            results.append(result)
        return results

    batch = blocking(_batch)
    batch_async = awaitable(_batch)

    def _nmt(self, node_id: int, command: Union[str, int]):
        """Send an NMT command to a node (0 = all): start, stop, preop, reset, reset-comm."""
        code = NMT_COMMANDS.get(command, command) if isinstance(command, str) else command
        if isinstance(code, str):
            raise ValueError(f'{command!r} is not an NMT command: use '
                             f'{", ".join(NMT_COMMANDS)} or its number')
        response = yield from self._call(NmtCommand, 'nmt_command', NmtCommand.Request(
            node_id=node_id, command=code))
        if not response.success:
            name = next((name for name, number in NMT_COMMANDS.items() if number == code), code)
            raise RequestFailed(f'NMT command {name} to node {node_id}', response)

    nmt = blocking(_nmt)
    nmt_async = awaitable(_nmt)

    def _state(self, node_id: int):
        """Return a node's state as it last reported it: the NmtState answer.

        Its ``state_name`` (e.g. ``OPERATIONAL``), ``state`` and ``last_seen_age`` (s; -1:
        never heard).
        """
        response = yield from self._call(NmtState, 'nmt_state', NmtState.Request(
            node_id=node_id))
        if not response.success:
            raise RequestFailed(f'state of node {node_id}', response)
        return response

    state = blocking(_state)
    state_async = awaitable(_state)

    def _newest(self, message_type, topic: str, qos, what: str):
        """Return the newest message of a latched topic of the gateway, subscribed once."""
        with self._lock:
            kept = self._latest.get(topic)
            subscribed = kept is not None
            if not subscribed:
                kept = self._latest[topic] = []
        if not subscribed:
            self._own.create_subscription(message_type, f'{self.gateway}/{topic}', kept.append,
                                          qos)
        if not (yield self._when(lambda: kept, self.wait)):
            raise GatewayUnavailable(f'no {what} from {self.gateway} within {self.wait:g} s: '
                                     f'is cbcan_node running?')
        newest = kept[-1]
        del kept[:-1]
        return newest

    def _node_states(self):
        """Return the latest ``node_states`` message (every known node, its state)."""
        return (yield from self._newest(NodeStates, 'node_states', NODE_STATES_QOS,
                                        'node states'))

    node_states = blocking(_node_states)
    node_states_async = awaitable(_node_states)

    def _states(self):
        """Return ``{node id: state name}`` of every node the gateway knows."""
        message = yield from self._node_states()
        return {node.node_id: node.state_name for node in message.nodes}

    states = blocking(_states)
    states_async = awaitable(_states)

    def _boot(self, node_id: int = 0, timeout: float = 0.0):
        """Run the boot of ``node_id`` again (0: every device); return the Boot answer.

        Its ``states`` (one ``BootState`` each) say what each boot found; raises
        RequestFailed when a boot failed or was refused. ``timeout``: seconds for the boots
        (0: 30 s).
        """
        response = yield from self._call(Boot, 'boot', Boot.Request(
            node_id=node_id, timeout=float(timeout)),
            (timeout or DEFAULT_CALL_TIMEOUT) + ANSWER_MARGIN)
        if not response.success:
            raise RequestFailed(f'boot of {f"node {node_id}" if node_id else "every device"}',
                                response)
        return response

    boot = blocking(_boot)
    boot_async = awaitable(_boot)

    def _boot_states(self):
        """Return the latest ``boot_states`` message (every booted device, its boot)."""
        return (yield from self._newest(BootStates, 'boot_states', BOOT_STATES_QOS,
                                        'boot states'))

    boot_states = blocking(_boot_states)
    boot_states_async = awaitable(_boot_states)

    def _program_download(self, node_id: int, file: str, program: int = 1,
                          expected_software_id: int = 0, start: bool = True, feedback=None):
        """Download the program image ``file`` into a device and start it (CiA 302-3).

        ``file`` is read by the gateway: a path on its machine. ``feedback(message)`` (a
        ``ProgramDownload.Feedback``: phase, bytes_sent, bytes_total, bytes_per_second) is
        called on the client's thread. Returns the ``ProgramDownload.Result`` (its
        ``software_id``); raises RequestFailed when the download was refused or failed (its
        message says what the device was left in), GatewayUnavailable when no gateway takes
        or answers it.
        """
        with self._lock:
            if self._downloads is None:
                self._downloads = FeedbackFirstActionClient(self._own, ProgramDownload,
                                               f'{self.gateway}/program_download')
            action = self._downloads
        if not (yield self._when(action.server_is_ready, self.wait)):
            raise GatewayUnavailable(f'no gateway at {self.gateway}: is cbcan_node running? '
                                     f'(waited {self.wait:g} s for program_download)')
        sent = action.send_goal_async(
            ProgramDownload.Goal(node_id=node_id, file=file, program=program,
                                 expected_software_id=expected_software_id, start=start),
            feedback_callback=(lambda message: feedback(message.feedback)) if feedback
            else None)
        if not (yield self._when(sent.done, self.wait + ANSWER_MARGIN)):
            raise GatewayUnavailable(f'{self.gateway}/program_download did not take the goal')
        answered = sent.result().get_result_async()
        while not (yield self._when(answered.done, PRESENCE_CHECK)):
            if not action.server_is_ready():
                raise GatewayUnavailable(f'{self.gateway} went away during the program '
                                         f'download to node {node_id}')
        result = answered.result().result
        if not result.success:
            raise RequestFailed(f'program download to node {node_id}', result)
        return result

    program_download = blocking(_program_download)
    program_download_async = awaitable(_program_download)


__all__ = ['GatewayClient', 'GatewayError', 'GatewayUnavailable', 'NMT_COMMANDS', 'Read',
           'RequestFailed', 'Result', 'Write', 'answer_within', 'describe']
