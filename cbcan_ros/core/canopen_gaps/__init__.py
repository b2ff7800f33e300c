"""Everything the gateway adds to canopen 2.4.1, in one place, to be offered upstream.

canopen's own classes are used; where they fall short for a gateway that must give every
request exactly one right answer, or take any vendor's file as it is, they are extended in
this package and nowhere else, one module per part of canopen. Each gap is listed in
docs/library_gaps.md.

- :mod:`.sdo_client`: the SDO client and its transfer streams (``StrictSdoClient``).
- :mod:`.local_node`: the gateway's own dictionary as a ``LocalNode`` on no bus.
- :mod:`.emcy`: ``EmcyConsumer`` for one device's EMCY frames.
- :mod:`.eds_import`: reading vendors' EDS and DCF files (``import_od``).
"""
