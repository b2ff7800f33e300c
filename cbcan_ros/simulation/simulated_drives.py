"""The simulated CiA 402 drives a gateway puts on its bus (``simulation.drives``).

They run on durand, which otherwise only the tests need, so a gateway without it still starts,
with its other simulated devices, and says why the drives are missing.
"""

from typing import Callable, List

# The PDO layouts a simulated drive can have (``simulation.drive_layout``; described in
# ``durand.drive_pdos``), each by the function there that makes it; the first is the default.
LAYOUTS = {
    'combined': 'default_drive_pdos',
    'vendor': 'vendor_drive_pdos',
    'ros2_canopen': 'ros2_canopen_drive_pdos',
    'sdo_only': 'sdo_only_drive_pdos',
}


def simulated_drives(node_ids: List[int], warn: Callable[[str], None],
                     layout: str = 'combined', **bus_options) -> list:
    """Return drives with the PDO ``layout`` of ``LAYOUTS``, not yet started.

    ``bus_options`` are those of :class:`DurandDrive` (interface, channel). Without durand,
    ``warn`` says so and none is returned.
    """
    try:
        from .durand.drive import DurandDrive
        from .durand.drive_pdos import drive_pdos
    except ModuleNotFoundError as error:
        if error.name != 'durand':
            raise
        warn(f'parameter simulation.drives: drives {node_ids} are not simulated: they need '
             f'the Python package durand (pip install durand==0.5.0)')
        return []
    return [DurandDrive(node_id, pdos=drive_pdos(layout), **bus_options)
            for node_id in node_ids]
