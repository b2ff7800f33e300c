"""SDO (CiA 301): reads, writes and batches of a device's objects, one channel per device.

Entry point: ``channel.SdoChannel`` (a device's queue and its transfers, ``transfer``);
``requests`` checks a request before the gateway routes it, ``abort_codes`` names every abort,
``write_protection`` holds the write rules, ``request_queue`` the deadlines and queues.
"""
