"""The simulated CiA 402 drives a gateway puts on its bus (``simulation.drives``).

They run on durand, which otherwise only the tests need, so a gateway without it still starts,
with its other simulated devices, and says why the drives are missing.
"""

from typing import Callable, List


def simulated_drives(node_ids: List[int], warn: Callable[[str], None],
                     **bus_options) -> list:
    """Return drives with the PDOs of a common drive (``durand_drive_pdos``), not yet started.

    ``bus_options`` are those of :class:`DurandDrive` (interface, channel). Without durand,
    ``warn`` says so and none is returned.
    """
    try:
        from .durand_drive import DurandDrive
        from .durand_drive_pdos import default_drive_pdos
    except ModuleNotFoundError as error:
        if error.name != 'durand':
            raise
        warn(f'parameter simulation.drives: drives {node_ids} are not simulated: they need '
             f'the Python package durand (pip install durand==0.5.0)')
        return []
    return [DurandDrive(node_id, pdos=default_drive_pdos(), **bus_options)
            for node_id in node_ids]
