"""Simulated CANopen devices: on python-canopen (``canopen_device``) and on durand."""
