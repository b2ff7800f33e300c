"""What the gateway adds to python-can 4.6.1's socket drivers, in one place.

python-can opens the bus; where its ``udp_multicast`` and ``socketcan`` drivers fall short for
a gateway (frames lost without a word, a system call more per frame, its own frames handed
back), the socket the driver keeps is adjusted here and nowhere else, one module per gap.
Each is listed in docs/library_gaps.md; the bus supervisor (``core/bus.py``) covers the
others (``Notifier``, ``slcan``, adapters' clocks).

- :mod:`.receive_buffer`: a receive buffer deep enough for a thread held up (both drivers).
- :mod:`.send_timeout`: the send timeout held by the kernel (``udp_multicast``).
- :mod:`.own_frames`: the gateway's own frames dropped by the kernel (``udp_multicast``).
"""
