"""The measuring side of the benchmark: every row, from the caller's point of view.

``python bench_client.py virtual``: ONE process holds everything on a python-can ``virtual``
bus: the simulated devices, the gateway (CbcanNode on the EventsExecutor of ``make_executor()``,
in a thread of its own, as ``cbcan_node`` spins it), the Trigger node (rclpy's default executor
in a thread of its own), raw python-canopen, and this client (one node, one
SingleThreadedExecutor on the main thread).

``python bench_client.py udp_multicast``: this client only; the devices, the Trigger server and
the installed ``cbcan_node`` are processes of their own, started by ``bench_sdo.py``, which
also serves this process's requests (stop the devices, start a load, measure CPU).

Calls are ``call_async`` followed by ``spin_once`` until ``future.done()``: never
``spin_until_future_complete`` (it slows down over thousands of calls, ros2/rclpy#1374) and
never ``add_done_callback`` (its race loses about one callback in 30). Rows that are compared
alternate call by call (latency) or round by round (bursts, batches, 64 KiB), so the drift of a
shared machine hits them alike.
"""

import argparse
import json
import random
import sys
import threading
import time
import uuid

from bench_util import (
    BATCH_DEVICES,
    BIG_TIMEOUT,
    BLOCK_DEVICE,
    DEVICE_TYPE,
    DOMAIN_DATA,
    DOMAIN_INDEX,
    DOMAIN_SIZE,
    dropped_between,
    exit_on_sigterm,
    import_retrying,
    latency,
    LATENCY_DEVICE,
    LOCAL_DEVICES,
    NMT_ENTER_PRE_OPERATIONAL,
    NMT_START,
    OPERATIONAL,
    PRE_OPERATIONAL,
    progress,
    rate,
    receive,
    SEGMENTED_DEVICE,
    send,
    STATE_DEVICE,
)
import canopen
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger

gateway_node_module, interface_module, srv, msg = import_retrying(
    'cbcan_ros.ros.node', 'cbcan_ros.ros.interface', 'cbcan_ros.srv', 'cbcan_ros.msg')
SERVICE_QOS = interface_module.SERVICE_QOS
NODE_STATES_QOS = interface_module.NODE_STATES_QOS

# Counts per row: (default, --quick)
COUNTS = {
    'warmup': (100, 30),
    'latency': (1000, 300),
    'burst_rounds': (3, 1),
    'batch_rounds': (3, 1),
    'segmented_rounds': (2, 1),
    'block_rounds': (3, 1),
    'state_samples': (30, 10),
    'cpu_window': (5.0, 3.0),
    'load_calls': (300, 100),
}
BURSTS = (150, 600)
BATCH_SIZE = 1000
STATE_TIMEOUT = 2.0
# A request's timeout covers its time in the device's queue: in a burst of 600 over 10
# devices, the default 0.5 s would time calls out and measure refusals, not throughput.
BURST_TIMEOUT = 10.0
SETTLE_AFTER_DEVICES = 3.5  # heartbeat.timeout (3 s): the old devices' timeouts are over
SETTLE_AFTER_LOAD = 1.5
LOAD_STAGES = (('base', 1, 200), ('32', 32, 100), ('127', 127, 10))


class Unanswered(Exception):
    """A call got no answer in time."""


class Caller:
    """Service calls from one node: call_async, then spin_once until the futures are done."""

    def __init__(self, node, executor):
        self.node = node
        self.executor = executor

    def client(self, service_type, name: str):
        """Return a client with SERVICE_QOS, once the service is there."""
        client = self.node.create_client(service_type, name, qos_profile=SERVICE_QOS)
        deadline = time.monotonic() + 30.0
        while not client.service_is_ready():
            if time.monotonic() > deadline:
                raise SystemExit(f'bench: service {name} did not appear within 30 s')
            self.executor.spin_once(timeout_sec=0.1)
        return client

    def call(self, client, request, timeout: float = 5.0):
        """Call and return the answer; raise Unanswered after ``timeout`` seconds."""
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                client.remove_pending_request(future)
                raise Unanswered(f'no answer from {client.srv_name} within {timeout:g} s')
            self.executor.spin_once(timeout_sec=0.05)
        return future.result()

    def burst(self, client, requests, timeout: float = 60.0):
        """Send every request at once; return (seconds until the last answer, answers).

        An answer missing after ``timeout`` is None (and its time is not counted).
        """
        start = time.perf_counter()
        futures = [client.call_async(request) for request in requests]
        pending = list(futures)
        deadline = time.monotonic() + timeout
        while pending and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
            pending = [future for future in pending if not future.done()]
        elapsed = time.perf_counter() - start
        for future in pending:
            client.remove_pending_request(future)
        return elapsed, [future.result() if future.done() else None for future in futures]

    def spin_for(self, seconds: float) -> None:
        """Serve callbacks (subscriptions) for ``seconds``."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=max(0.0, min(0.05, deadline - time.monotonic())))


class RawSide:
    """Raw python-canopen on the same bus: RemoteNodes without a dictionary."""

    def __init__(self, bus: dict):
        self._bus = bus
        self.network = None
        self.remotes = {}
        # (time.time() of the frame, state) of every change in STATE_DEVICE's heartbeat: the
        # bus's own timestamp (udp_multicast: the kernel's receive time; virtual: send time)
        self.state_frames = []
        self._last_state = None

    def connect(self) -> None:
        """Open the bus (the raw rows need it; bursts and batches run without it)."""
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(**self._bus)
        self.remotes = {}
        for node_id in (LATENCY_DEVICE, SEGMENTED_DEVICE, BLOCK_DEVICE):
            remote = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            self.network.add_node(remote)
            self.remotes[node_id] = remote
        self.network.subscribe(0x700 + STATE_DEVICE, self._on_heartbeat)

    def disconnect(self) -> None:
        """Leave the bus."""
        if self.network is not None:
            self.network.disconnect()
            self.network = None

    def _on_heartbeat(self, _can_id, data, timestamp) -> None:
        if data:
            state = data[0] & 0x7F
            if state != self._last_state:
                self.state_frames.append((timestamp or time.time(), state))
                self._last_state = state

    def parallel_uploads(self, node_ids, total: int) -> int:
        """Upload 0x1000 ``total`` times over ``node_ids``, one thread per device; return right.

        What raw python-canopen reaches on this machine and bus with the devices the batch
        rows use: the ceiling a batch is measured against.
        """
        remotes = []
        for node_id in node_ids:
            if node_id not in self.network:
                self.network.add_node(canopen.RemoteNode(node_id, canopen.ObjectDictionary()))
            remotes.append(self.network[node_id])
        right = [0] * len(remotes)

        def uploads(position: int) -> None:
            for _ in range(total // len(remotes)):
                try:
                    if remotes[position].sdo.upload(0x1000, 0) == DEVICE_TYPE:
                        right[position] += 1
                except canopen.SdoError:
                    pass

        threads = [threading.Thread(target=uploads, args=(position,))
                   for position in range(len(remotes))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return sum(right)

    def read_device_type(self) -> bytes:
        """Upload 0x1000 of the latency device (expedited)."""
        return self.remotes[LATENCY_DEVICE].sdo.upload(0x1000, 0)

    def read_segmented(self) -> bytes:
        """Upload the 64 KiB DOMAIN segmented."""
        return self.remotes[SEGMENTED_DEVICE].sdo.upload(DOMAIN_INDEX, 0)

    def read_block(self) -> bytes:
        """Upload the 64 KiB DOMAIN by block transfer (with CRC, as the gateway asks)."""
        stream = self.remotes[BLOCK_DEVICE].sdo.open(
            DOMAIN_INDEX, 0, 'rb', block_transfer=True, request_crc_support=True)
        try:
            return stream.read()
        finally:
            stream.close()


class Suite:
    """Every row of one column; results go to the main process as they are measured."""

    def __init__(self, column: str, caller: Caller, namespace: str, raw: RawSide,
                 quick: bool, hub: bool):
        self.column = column
        self.caller = caller
        self.raw = raw
        self.quick = quick
        self.hub = hub
        gateway = f'{namespace}/cbcan'
        self.trigger = caller.client(Trigger, f'{namespace}/trigger')
        self.sdo_read = caller.client(srv.SdoRead, f'{gateway}/sdo_read')
        self.floor_sdo_read = caller.client(srv.SdoRead, f'{namespace}/floor_sdo_read')
        self.sdo_batch = caller.client(srv.SdoBatch, f'{gateway}/sdo_batch')
        self.states = []  # (time.time(), state of STATE_DEVICE) of every NodeStates message
        self.udp_drops = {}  # phase: {process: datagrams its socket dropped (full buffer)}
        caller.node.create_subscription(msg.NodeStates, f'{gateway}/node_states',
                                        self._on_states, NODE_STATES_QOS)

    def count(self, name: str):
        """Return the count of ``name`` for this run (default or --quick)."""
        return COUNTS[name][1 if self.quick else 0]

    def row(self, name: str, data: dict) -> None:
        """Hand a measured row to the main process."""
        send({'row': name, 'column': self.column, 'data': data})

    def run(self) -> None:
        """Measure every row of the column."""
        self.raw.connect()
        try:
            self.phase('warm-up', self.warm_up)
            self.phase('latency', self.measure_latency)
            self.phase('64 KiB', self.measure_64k)
            self.phase('node_states', self.measure_node_states)
        finally:
            self.raw.disconnect()
        self.phase('bursts', self.measure_bursts)
        self.phase('batches', self.measure_batches)
        if self.hub:
            self.row('udp_drops', {'kind': 'info', 'phases': self.udp_drops})
            self.measure_load()

    def phase(self, name: str, measure) -> None:
        """Run one phase; on udp_multicast, count the frames each process's socket dropped."""
        before = self.ask({'op': 'udp_drops'}) if self.hub else {}
        measure()
        if self.hub:
            after = self.ask({'op': 'udp_drops'})
            self.udp_drops[name] = dropped_between(before, after)

    # ------------------------------------------------------------ helpers

    def _on_states(self, message) -> None:
        for node in message.nodes:
            if node.node_id == STATE_DEVICE:
                self.states.append((time.time(), node.state))

    @staticmethod
    def _read(node_id: int, index: int = 0x1000, timeout: float = 0.0):
        return srv.SdoRead.Request(node_id=node_id, index=index, subindex=0, timeout=timeout)

    @staticmethod
    def _right(answer, expected: bytes = DEVICE_TYPE) -> bool:
        return answer is not None and answer.success and bytes(answer.data) == expected

    def _call_read(self, node_id: int, failures: list, client=None) -> None:
        try:
            answer = self.caller.call(client or self.sdo_read, self._read(node_id))
        except Unanswered as error:
            failures.append(str(error))
            return
        if not self._right(answer):
            failures.append(answer.message or bytes(answer.data).hex())

    # ------------------------------------------------------------ rows 1-3: latency

    def warm_up(self) -> None:
        """Reach every device once (so block-refusing devices fall back), then warm up."""
        progress(f'{self.column}: warming up')
        failures = []
        for node_id in LOCAL_DEVICES:
            self._call_read(node_id, failures)
        for _ in range(self.count('warmup')):
            self.raw.read_device_type()
            self.caller.call(self.trigger, Trigger.Request())
            self._call_read(LATENCY_DEVICE, failures, self.floor_sdo_read)
            self._call_read(LATENCY_DEVICE, failures)
        if failures:
            progress(f'{self.column}: {len(failures)} warm-up reads failed, e.g. {failures[0]}')

    def measure_latency(self) -> None:
        """Rows 1-3: raw upload, Trigger, the read's floor and sdo_read, alternating.

        The floor (``bench_trigger.FloorSdoRead``) is a bare rclpy service whose callback
        makes the raw upload: what any gateway of rclpy and python-canopen pays at least.
        """
        count = self.count('latency')
        progress(f'{self.column}: latency, {count} calls a row, alternating')
        times = {'raw': [], 'trigger': [], 'floor_sdo_read': [], 'sdo_read': []}
        failures = {name: [] for name in times}

        def raw():
            if self.raw.read_device_type() != DEVICE_TYPE:
                failures['raw'].append('raw upload returned other bytes')

        def trigger():
            try:
                if not self.caller.call(self.trigger, Trigger.Request()).success:
                    failures['trigger'].append('Trigger answered success false')
            except Unanswered as error:
                failures['trigger'].append(str(error))

        def sdo_read():
            self._call_read(LATENCY_DEVICE, failures['sdo_read'])

        def floor():
            self._call_read(LATENCY_DEVICE, failures['floor_sdo_read'], self.floor_sdo_read)

        steps = [('raw', raw), ('trigger', trigger), ('floor_sdo_read', floor),
                 ('sdo_read', sdo_read)]
        for i in range(count):
            turn = i % len(steps)
            for name, step in steps[turn:] + steps[:turn]:  # rotate who goes first
                start = time.perf_counter()
                step()
                times[name].append(time.perf_counter() - start)
        for name in times:
            self.row(name, latency(times[name], right=count - len(failures[name]),
                                   calls=count, errors=failures[name][:3]))

    # ------------------------------------------------------------ row 3: bursts

    def measure_bursts(self) -> None:
        """Row 3: bursts of concurrent Trigger and sdo_read calls, alternating by round."""
        rounds = self.count('burst_rounds')
        progress(f'{self.column}: bursts of {BURSTS} calls, {rounds} rounds')
        keys = [(kind, size) for kind in ('trigger', 'sdo') for size in BURSTS]
        rates = {key: [] for key in keys}
        right = {key: 0 for key in keys}
        answered = {key: 0 for key in keys}
        errors = {key: [] for key in keys}
        # One untimed burst of each first: the first burst of a client pays for allocations.
        self.caller.burst(self.trigger, [Trigger.Request() for _ in range(BURSTS[0])])
        self.caller.burst(self.sdo_read, [self._read(LOCAL_DEVICES[i % len(LOCAL_DEVICES)])
                                          for i in range(BURSTS[0])])
        for round_number in range(rounds):
            for size in BURSTS:
                kinds = ('trigger', 'sdo') if round_number % 2 == 0 else ('sdo', 'trigger')
                for kind in kinds:
                    if kind == 'trigger':
                        client, expected = self.trigger, None
                        requests = [Trigger.Request() for _ in range(size)]
                    else:
                        client, expected = self.sdo_read, DEVICE_TYPE
                        requests = [self._read(LOCAL_DEVICES[i % len(LOCAL_DEVICES)],
                                               timeout=BURST_TIMEOUT)
                                    for i in range(size)]
                    elapsed, answers = self.caller.burst(client, requests)
                    bad = [a for a in answers if a is None or not a.success or (
                        expected is not None and bytes(a.data) != expected)]
                    key = (kind, size)
                    rates[key].append(size / elapsed)
                    right[key] += size - len(bad)
                    answered[key] += sum(a is not None for a in answers)
                    errors[key] += ['unanswered' if a is None else (a.message or 'other data')
                                    for a in bad][:3]
                    self.caller.spin_for(0.05)
        for (kind, size), values in rates.items():
            key = (kind, size)
            self.row(f'burst_{kind}_{size}', rate(
                values, 'calls/s', right=right[key], calls=size * rounds,
                answered=answered[key], errors=errors[key][:3]))

    # ------------------------------------------------------------ row 4: batches

    def measure_batches(self) -> None:
        """Row 4: sdo_batch of 1000 reads of 0x1000 over 1, 3 and 8 devices."""
        rounds = self.count('batch_rounds')
        progress(f'{self.column}: sdo_batch of {BATCH_SIZE} reads, {rounds} rounds')
        rates = {devices: [] for devices in BATCH_DEVICES}
        right = {devices: 0 for devices in BATCH_DEVICES}
        errors = {devices: [] for devices in BATCH_DEVICES}
        raw_rates, raw_right = [], 0
        raw_devices = BATCH_DEVICES[3]
        raw_total = BATCH_SIZE - BATCH_SIZE % len(raw_devices)
        self.raw.connect()
        for round_number in range(rounds):
            start = time.perf_counter()
            raw_right += self.raw.parallel_uploads(raw_devices, raw_total)
            raw_rates.append(raw_total / (time.perf_counter() - start))
            order = list(BATCH_DEVICES)
            if round_number % 2:
                order.reverse()
            for devices in order:
                node_ids = BATCH_DEVICES[devices]
                request = srv.SdoBatch.Request(timeout=BIG_TIMEOUT, accesses=[
                    msg.SdoAccess(node_id=node_ids[i % len(node_ids)], index=0x1000)
                    for i in range(BATCH_SIZE)])
                start = time.perf_counter()
                try:
                    answer = self.caller.call(self.sdo_batch, request, BIG_TIMEOUT + 5.0)
                except Unanswered as error:
                    errors[devices].append(str(error))
                    continue
                elapsed = time.perf_counter() - start
                good = [r for r in answer.results if r.success and bytes(r.data) == DEVICE_TYPE]
                errors[devices] += [r.message for r in answer.results if not r.success][:3]
                right[devices] += len(good)
                rates[devices].append(BATCH_SIZE / elapsed)
                self.caller.spin_for(0.05)
        self.raw.disconnect()
        self.row('batch_raw_3', rate(raw_rates, 'SDO/s', right=raw_right,
                                     calls=raw_total * rounds))
        for devices, values in rates.items():
            self.row(f'batch_{devices}', rate(values, 'SDO/s', right=right[devices],
                                              calls=BATCH_SIZE * rounds,
                                              errors=errors[devices][:3]))

    # ------------------------------------------------------------ row 5: 64 KiB

    def measure_64k(self) -> None:
        """Row 5: 64 KiB segmented and block reads, service against raw, alternating."""
        for kind, node_id, raw_read, rounds in (
                ('segmented', SEGMENTED_DEVICE, self.raw.read_segmented,
                 self.count('segmented_rounds')),
                ('block', BLOCK_DEVICE, self.raw.read_block, self.count('block_rounds'))):
            progress(f'{self.column}: 64 KiB {kind} read, raw and service, {rounds} rounds')
            rates = {'raw': [], 'service': []}
            errors = {'raw': [], 'service': []}

            def service(node_id=node_id):
                return self.caller.call(self.sdo_read, self._read(
                    node_id, DOMAIN_INDEX, BIG_TIMEOUT), BIG_TIMEOUT + 5.0)

            for round_number in range(rounds):
                steps = [('raw', raw_read), ('service', service)]
                if round_number % 2:
                    steps.reverse()
                for name, step in steps:
                    start = time.perf_counter()
                    try:
                        answer = step()
                    except Exception as error:  # noqa: BLE001 - a failed transfer is a result
                        errors[name].append(f'{type(error).__name__}: {error}')
                        continue
                    elapsed = time.perf_counter() - start
                    data = answer if name == 'raw' else (
                        bytes(answer.data) if answer.success else None)
                    if data != DOMAIN_DATA:
                        errors[name].append(answer.message if name == 'service' else
                                            f'{len(data)} bytes, not the 64 KiB written')
                        continue
                    rates[name].append(DOMAIN_SIZE / 1024 / elapsed)
            for name, values in rates.items():
                self.row(f'{kind}_{name}', rate(values, 'KiB/s', right=len(values),
                                                calls=rounds, errors=errors[name][:3]))

    # ------------------------------------------------------------ row 6: node_states

    def measure_node_states(self) -> None:
        """Row 6: a device's heartbeat changing state -> NodeStates arriving here."""
        samples = self.count('state_samples')
        progress(f'{self.column}: node_states latency, {samples} state changes')
        from_frame, from_command, errors = [], [], []
        self.caller.spin_for(0.5)  # the transient-local message and a few heartbeats
        target = OPERATIONAL
        for _ in range(samples):
            command = NMT_START if target == OPERATIONAL else NMT_ENTER_PRE_OPERATIONAL
            self.states.clear()
            commanded = time.time()
            self.raw.network.send_message(0, bytes([command, STATE_DEVICE]))
            deadline = time.monotonic() + STATE_TIMEOUT
            arrived = frame = None
            while (arrived is None or frame is None) and time.monotonic() < deadline:
                self.caller.executor.spin_once(timeout_sec=0.01)
                arrived = next((t for t, state in self.states if state == target), None)
                frame = next((t for t, state in list(self.raw.state_frames)
                              if state == target and t >= commanded), None)
            if arrived is None or frame is None:
                errors.append(f'state {target} not seen on the '
                              f'{"topic" if arrived is None else "bus"} within '
                              f'{STATE_TIMEOUT:g} s')
            else:
                from_frame.append(arrived - frame)
                from_command.append(arrived - commanded)
            target = PRE_OPERATIONAL if target == OPERATIONAL else OPERATIONAL
            self.caller.spin_for(random.uniform(0.02, 0.07))
        self.row('states_frame', latency(from_frame, right=len(from_frame), calls=samples,
                                         errors=errors[:3]))
        self.row('states_command', latency(from_command, right=len(from_command),
                                           calls=samples, errors=errors[:3]))

    # ------------------------------------------------------------ row 6: load (udp only)

    def ask(self, request: dict) -> dict:
        """Ask the main process to do something (devices, load, CPU window); its answer."""
        send({'request': request})
        return receive()

    def measure_load(self) -> None:
        """Row 6: CPU and RSS of the idle node, and sdo_read p50, under heartbeat loads."""
        window = self.count('cpu_window')
        calls = self.count('load_calls')
        progress(f'{self.column}: load: the device process leaves, the load process comes')
        self.ask({'op': 'start_load'})
        self.caller.spin_for(SETTLE_AFTER_DEVICES)
        for name, nodes, period in LOAD_STAGES:
            progress(f'{self.column}: load {name}: {nodes} nodes every {period} ms, '
                     f'{window:g} s CPU window, then {calls} sdo_read calls')
            self.ask({'op': 'load', 'nodes': nodes, 'period_ms': period})
            self.caller.spin_for(SETTLE_AFTER_LOAD)
            cpu = self.ask({'op': 'cpu', 'seconds': window})
            times, failures = [], []
            drops = self.ask({'op': 'udp_drops'})
            for _ in range(calls):
                start = time.perf_counter()
                self._call_read(1, failures)
                times.append(time.perf_counter() - start)
            drops_after = self.ask({'op': 'udp_drops'})
            dropped = {f'calls_drops_{key}': count
                       for key, count in dropped_between(drops, drops_after).items()}
            self.row(f'load_{name}', latency(
                times, right=calls - len(failures), calls=calls, errors=failures[:3],
                nodes=nodes, period_ms=period, **cpu, **dropped))


class Spinner:
    """Spins one node on a thread of its own, ``spin_once`` at a time, until stopped."""

    def __init__(self, node, executor):
        self._executor = executor
        self._executor.add_node(node)
        self._spinning = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self._spinning:
            self._executor.spin_once(timeout_sec=0.5)

    def stop(self) -> None:
        """End the spinning, then shut the executor down (as cbcan_node does)."""
        self._spinning = False
        self._executor.wake()
        self._thread.join(timeout=5.0)
        self._executor.shutdown(timeout_sec=2.0)


def run_virtual(args) -> None:
    """Run everything in this one process on a python-can virtual bus."""
    from bench_devices import DeviceHost
    from bench_trigger import FloorSdoRead, TriggerNode
    from bench_util import BLOCK_DEVICE as DURAND_ID
    from rclpy.parameter import Parameter

    channel = f'bench-{uuid.uuid4().hex[:8]}'
    namespace = f'/bench_{uuid.uuid4().hex[:8]}'
    host = DeviceHost('virtual', channel, {}, LOCAL_DEVICES, DURAND_ID)
    host.start()
    rclpy.init()
    spinners, nodes, floor = [], [], None
    try:
        gateway = gateway_node_module.CbcanNode(namespace=namespace, parameter_overrides=[
            Parameter('can.interface', value='virtual'),
            Parameter('can.channel', value=channel),
            Parameter('sdo.block_transfer', value=True)])
        nodes.append(gateway)
        trigger = TriggerNode(namespace, SERVICE_QOS)
        nodes.append(trigger.node)
        floor = FloorSdoRead(namespace, SERVICE_QOS, {'interface': 'virtual',
                                                      'channel': channel})
        nodes.append(floor.node)
        # The gateway and the floor of a read on the executor cbcan_node uses, the Trigger on
        # rclpy's default one.
        spinners += [Spinner(gateway, gateway_node_module.make_executor()),
                     Spinner(floor.node, gateway_node_module.make_executor()),
                     Spinner(trigger.node, SingleThreadedExecutor())]
        client_node = rclpy.create_node(f'bench_client_{uuid.uuid4().hex[:8]}')
        nodes.append(client_node)
        executor = SingleThreadedExecutor()
        executor.add_node(client_node)
        caller = Caller(client_node, executor)
        raw = RawSide({'interface': 'virtual', 'channel': channel})
        Suite('virtual', caller, namespace, raw, args.quick, hub=False).run()
        executor.shutdown(timeout_sec=1.0)
    finally:
        for spinner in spinners:
            spinner.stop()
        if floor is not None:
            floor.close()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        host.stop()


def run_udp(args) -> None:
    """Run this client only; the rest are processes of their own on udp_multicast."""
    rclpy.init()
    client_node = rclpy.create_node(f'bench_client_{uuid.uuid4().hex[:8]}')
    executor = SingleThreadedExecutor()
    executor.add_node(client_node)
    try:
        caller = Caller(client_node, executor)
        raw = RawSide({'interface': 'udp_multicast', 'channel': args.channel,
                       **json.loads(args.bus_options)})
        Suite('udp_multicast', caller, args.namespace, raw, args.quick, hub=True).run()
    finally:
        executor.shutdown(timeout_sec=1.0)
        client_node.destroy_node()
        rclpy.try_shutdown()


def main(argv=None) -> int:
    """Measure one column; rows go to standard output as ``@@`` lines."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('column', choices=('virtual', 'udp_multicast'))
    parser.add_argument('--namespace', default='')
    parser.add_argument('--channel', default='')
    parser.add_argument('--bus-options', default='{}')
    parser.add_argument('--quick', action='store_true')
    args = parser.parse_args(argv)
    exit_on_sigterm()
    try:
        (run_virtual if args.column == 'virtual' else run_udp)(args)
    except KeyboardInterrupt:
        return 130
    send({'done': True})
    return 0


if __name__ == '__main__':
    sys.exit(main())
