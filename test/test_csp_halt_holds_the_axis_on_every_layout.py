"""A CSP halt right after the axis reached its target leaves it there, on every layout.

The drive ignores the halt bit in CSP (several vendors' drives do), so the halt also writes
a position target: where the axis stands. Once a defect: on the vendor layout (several
TPDOs a cycle) a position TPDO the drive sent before it acted on the target arrived after
it, counted as "shown since", and 14 of 15 halts sent the axis back by its last step.
"""

from std_msgs.msg import Float64
from test_drive_layouts import layout, layout_pdos  # noqa: F401 - layout is a fixture
from test_drives import CSP, rig, SCALE, WAIT  # noqa: F401 - rig is a fixture

from conftest import wait_until

STEP = 300  # counts, far outside the default position window (10)
STEPS = 15


def test_a_csp_halt_right_after_the_axis_reached_its_target_leaves_it_there(rig, layout):  # noqa: F811
    axis = rig(pdos=layout_pdos(layout), **{'drives.command_timeout': 0.0})
    axis.drive.halts_in_cyclic_modes = False  # bit 8 without function in CSP (vendors)
    axis.enable(CSP)
    moved = []
    for step in range(STEPS):
        here = axis.drive.position
        axis.target.publish(Float64(data=(here + STEP) / SCALE))
        wait_until(lambda here=here: axis.drive.position == here + STEP, WAIT,
                   'the drive at its target')
        halted = axis.command('halt')  # the axis stands at here + STEP
        assert halted.success, halted.message
        if axis.drive.position != here + STEP:
            moved.append(f'step {step}: stood at {here + STEP}, halt moved it to '
                         f'{axis.drive.position} ({halted.message})')
        resumed = axis.command('resume')
        assert resumed.success, resumed.message
    assert not moved, f'{len(moved)} of {STEPS} halts moved the axis: {moved}'
