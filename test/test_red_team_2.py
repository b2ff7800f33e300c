"""Red-team regressions, second pass: the deferred answer path, seen from outside the process.

The SDO services answer from the thread that resolves the gateway's future (ros/deferred.py).
Each test starts the installed ``cbcan_node`` as a separate process (test/node_process.py) and
calls it from rclpy clients in this process or in child processes.
"""

import signal
import subprocess
import sys

from test_process_faults import namespace

from cbcan_ros.srv import SdoRead, SdoWrite

from conftest import HEAVY, new_channel, wait_for_future, wait_until
from node_process import service_client, START_TIMEOUT

pytestmark = HEAVY

# A client in a process of its own: one answered call, so its response reader is matched to
# the node's response writer, then it waits to be killed.
CLIENT = """
import sys
import rclpy
from cbcan_ros.ros.interface import SERVICE_QOS
from cbcan_ros.srv import SdoRead
rclpy.init()
node = rclpy.create_node('doomed_client')
client = node.create_client(SdoRead, sys.argv[1], qos_profile=SERVICE_QOS)
assert client.wait_for_service(timeout_sec=15.0)
future = client.call_async(SdoRead.Request(node_id=0, index=0x1000))
rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
print('answered' if future.done() else 'no answer', flush=True)
sys.stdin.read()
"""

# More answers than the response writer of a KEEP_ALL service keeps unacknowledged (Fast DDS:
# resource_limits.max_samples 5000), sent in bursts that each must be answered in time.
BURSTS = 11
BURST = 500


def test_a_killed_client_does_not_mute_the_service_for_the_others(start_node, client_node):
    # Once a defect, found by the second red-team pass: a client process killed (kill -9, a
    # crash, a lost robot computer) stays matched until its DDS lease runs out (about 20 s).
    # Its response reader never acknowledges, so a keep-all response writer kept every answer
    # to every caller; after 5000 of them each further answer failed to leave, unlogged, and
    # every other caller waited in vain until the lease ended.
    name = f'{namespace()}/cbcan'
    gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                          '-p', f'can.channel:={new_channel()}'])
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    doomed = subprocess.Popen([sys.executable, '-c', CLIENT, f'{name}/sdo_read'],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert doomed.stdout.readline().strip() == 'answered'
    finally:
        doomed.kill()
        doomed.wait(START_TIMEOUT)
        doomed.stdin.close()
        doomed.stdout.close()

    request = SdoRead.Request(node_id=0, index=0x1018, subindex=2)
    for burst in range(BURSTS):
        calls = [sdo_read.call_async(request) for _ in range(BURST)]
        wait_until(lambda calls=calls: all(call.done() for call in calls), 3.0,
                   f'the answers of burst {burst + 1} of {BURSTS} ({BURST} calls) after a '
                   f'client was killed')
        assert all(call.result().success for call in calls)
    assert gateway.process.poll() is None, gateway.output()


# Requests that take the node's executor long to take (deserialize): a signal then lands
# while it is between taking a request and triggering its guard condition.
LARGE = 4_000_000
IN_FLIGHT = 40
ATTEMPTS = 5


def test_signal_while_the_executor_is_busy_taking_requests_leaves_no_traceback(
        start_node, client_node):
    # Once a defect, found by the second red-team pass: main() stopped the executor with
    # executor.shutdown() while the executor thread was inside spin_once. rclpy 7.1 does not
    # wait there for the running callback and destroys its guard condition at once, so the
    # executor thread dies with InvalidHandle ("destruction was requested") or AttributeError
    # ("'NoneType' object has no attribute 'handle'") and a traceback on the node's output.
    # A race: each attempt hits it about every other time, so the test makes several.
    request = SdoWrite.Request(node_id=200, index=0x2000, data=bytes(LARGE))
    for attempt in range(ATTEMPTS):
        name = f'{namespace()}/cbcan'
        gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                              '-p', f'can.channel:={new_channel()}'])
        sdo_write = service_client(client_node, SdoWrite, f'{name}/sdo_write', gateway)
        assert not wait_for_future(sdo_write.call_async(request), 5.0).success
        calls = [sdo_write.call_async(request) for _ in range(IN_FLIGHT)]
        wait_until(lambda calls=calls: any(call.done() for call in calls), 5.0,
                   'the first answer of the burst')
        gateway.process.send_signal(signal.SIGTERM)
        status = gateway.wait(2.0)
        output = gateway.output()
        assert status == 0, output
        assert 'Traceback' not in output and 'Exception' not in output, \
            f'attempt {attempt + 1}:\n{output}'
