"""Program download (CiA 302-3): a device's firmware replaced through its 0x1F50 objects.

Entry point: :class:`.service.ProgramService` (one download per device at a time, each on a
thread of its own); :mod:`.download` holds the steps of one download, which the boot process
runs too (``software_file`` in the bus description).
"""
