"""Simulated CANopen devices and CiA 402 drives on durand, the independent device stack.

Entry points: ``device.DurandDevice`` and ``drive.DurandDrive``; ``drive_pdos`` holds the
drives' PDO layouts, the other modules mend or extend durand 0.5.0 (``network``,
``scheduler``, ``pdos``, ``dictionary``, ``heartbeat_consumer``).
"""
