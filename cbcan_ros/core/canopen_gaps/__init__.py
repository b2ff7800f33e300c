"""Everything the gateway adds to canopen 2.4.1, in one place, to be offered upstream.

canopen's own classes are used; where they fall short for a gateway that must give every
request exactly one right answer, or take any vendor's file as it is, they are extended in
this package and nowhere else, one module per part of canopen. Each gap is listed in
docs/library_gaps.md.

- :mod:`.sdo_client`: the SDO client and its transfer streams (``StrictSdoClient``).
- :mod:`.local_node`: the gateway's own dictionary as a ``LocalNode`` on no bus.
- :mod:`.emcy`: ``EmcyConsumer`` for one device's EMCY frames.
- :mod:`.eds_import`: reading vendors' EDS and DCF files (``import_od``).

The gateway refuses to start on another canopen release (``version_problem``): these
extensions reach into canopen's internals, which a release may change.
"""

import canopen

# The canopen releases whose internals this package extends: 2.4.x (tested: 2.4.1).
SUPPORTED = (2, 4)


def version_problem(version: str = '') -> str:
    """Return why canopen ``version`` (default: the one installed) cannot be used, or ''."""
    version = version or canopen.__version__
    try:
        major_minor = tuple(int(part) for part in version.split('.')[:2])
    except ValueError:
        major_minor = ()
    if major_minor == SUPPORTED:
        return ''
    wanted = '.'.join(map(str, SUPPORTED))
    return (f'canopen {version} is installed, but cbcan_ros supports canopen {wanted}.x only '
            f'(cbcan_ros/core/canopen_gaps extends its {wanted} internals): '
            f"pip install 'canopen=={wanted}.1'")
