"""PDOs and SYNC (CiA 301): mappings read from devices, frames sent and received, SYNC produced.

Entry point: ``service.PdoService``; ``mapping`` decodes and encodes frames by a mapping,
``parameters`` reads and writes a device's PDO parameters, ``sync`` produces SYNC.
"""
