"""CiA 402 drives: run as joints, commanded, watched and stopped safely.

Entry point: ``service.DriveService``. ``cia402`` is the profile's vocabulary (states,
controlwords, objects); ``commands`` the command sequences, ``objects`` and ``frames`` how a
write reaches the drive, ``status`` and ``checks`` what is known and what is refused,
``safety`` and ``standstill`` the stops, ``cycle`` the feedback cycle, ``arrival`` where a
move may go and whether it got there.
"""
