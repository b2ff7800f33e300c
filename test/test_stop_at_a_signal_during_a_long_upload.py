"""A signal while a long SDO upload from the drive is under way: the drive still gets its stop.

The node runs as its own process (test_drive_safety's rig). A robot program reads a large
DOMAIN of the enabled drive (segmented, thousands of frames); the signal comes in the middle
of it. The quick stop by SDO must reach the drive: a channel that keeps the stop queued
behind the upload until the stop's own wait ends sends it never (the node logs "waited 0.5 s
behind earlier requests to node 7; nothing was sent") and the drive runs on until its
own heartbeat consumer stops it (never, with drives.keep_running_if_gateway_dies).
"""

import signal

from test_drive_safety import (  # noqa: F401 (rig: a fixture)
    ANSWER,
    NODE,
    QUICK_STOP,
    rig,
    SDO_RESPONSE,
    stop_frame_after,
    stop_with,
)

from cbcan_ros.simulation.durand.dictionary import DOMAIN_INDEX
from cbcan_ros.srv import SdoRead

LARGE = bytes(range(256)) * 256  # 64 KiB (the most the DOMAIN holds): 9363 segments


def test_a_signal_during_a_long_upload_still_stops_the_drive(rig):  # noqa: F811
    axis = rig('-p', 'drives.command_timeout:=0.0')
    axis.enable_moving()
    axis.drive.set_value(DOMAIN_INDEX, 0, LARGE)
    read = axis.client(SdoRead, 'sdo_read')
    since = axis.recorder.mark()
    pending = read.call_async(SdoRead.Request(node_id=NODE, index=DOMAIN_INDEX, subindex=0,
                                              timeout=60.0))
    # Upload segments flowing (scs 0: upload segment response).
    segment = axis.recorder.first(lambda m: m.arbitration_id == SDO_RESPONSE
                                  and m.data[0] >> 5 == 0, 'an upload segment', since)
    segments = axis.recorder.first(
        lambda m: m.arbitration_id == SDO_RESPONSE and m.data[0] >> 5 == 0,
        'upload segments', segment + 200)
    assert not pending.done()
    stop_with(axis, signal.SIGINT)
    try:
        stop_frame_after(axis, QUICK_STOP, segments)
    except AssertionError as error:
        raise AssertionError(f'{str(error)[:300]}\n{axis.node.output()[-1500:]}') from None
