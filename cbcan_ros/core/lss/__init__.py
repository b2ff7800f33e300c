"""Layer setting services (CiA 305): finding unconfigured devices, giving them ids and rates.

Entry point: ``master.LssMaster``; ``requests`` checks what is asked and holds the answers,
``frames`` sends and receives the LSS frames.
"""
