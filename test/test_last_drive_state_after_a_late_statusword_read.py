"""The state a drive is last shown at shutdown is the one shutdown decided.

Shutdown sends each powered drive its stop, then waits up to SHUTDOWN_WAIT for its statusword
to show it; a drive whose statusword no TPDO brings is read once by SDO. A drive that shows no
stop in time is shown UNKNOWN: its subscribers' last drive_state. Here the drive has no PDOs
(sdo_only) and ignores the stop: the answer of that read, OPERATION_ENABLED, comes just after
the wait ended (an SDO answer in flight as the wait timed out; here it is held back). Once
a defect: it was taken and told, so the last state the node showed of the drive it had
stopped was OPERATION_ENABLED.
"""

from concurrent.futures import Future
import threading

from test_drives import CSV, NODE, Rig, WAIT

from cbcan_ros.core.drives import cia402
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos

RUNNING = 0x1637  # OPERATION_ENABLED, as the simulated drive shows it while it turns


def test_a_statusword_read_answered_after_shutdown_decided_is_not_shown(ros_context,
                                                                        start_durand):
    axis = Rig(start_durand, pdos=drive_pdos('sdo_only'))
    try:
        axis.enable(CSV)
        gateway = axis.gateway.node.gateway
        drives = gateway.drives
        drive = drives._drives[NODE]
        told, held = [], []
        drives.add_listener(lambda status: told.append(status.state)
                            if status.node_id == NODE else None)
        real_read = drive.objects.read

        def read(indexes, timeout):
            if not drives._closing or list(indexes) != [cia402.STATUSWORD]:
                return real_read(indexes, timeout)
            late = Future()  # the drive's answer: still running, it ignored the stop
            held.append(late)
            return late
        drive.objects.read = read
        stopping = threading.Thread(target=drives.stop)
        stopping.start()
        stopping.join(WAIT)
        assert held, 'no statusword read at shutdown'
        assert told and told[-1] == cia402.UNKNOWN, told
        held[0].set_result({cia402.STATUSWORD: RUNNING})
        assert told[-1] != cia402.OPERATION_ENABLED, (
            f'the drive stopped at shutdown was last shown {told[-1]} ({told[-4:]})')
    finally:
        axis.close()
