"""The stage a rig looks at: its performance volume.

Stage frame (``hardware.rig``): metres, z up, origin at the stage centre on the floor. Calibration
samples the volume to check a placement; a shot renders only the Gaussians inside it.
"""

from __future__ import annotations

from collections.abc import Sequence

#: an axis-aligned box ``((x0, y0, z0), (x1, y1, z1))``, metres, stage frame
Box = tuple[tuple[float, float, float], tuple[float, float, float]]


def stage_volume(stage_size_m: Sequence[float], floor_clearance_m: float = 0.03) -> Box:
    """The performance volume of a rig's stage (centred on the origin, floor at z = 0): the box
    ``[-x/2, x/2] × [-y/2, y/2] × [floor_clearance, height]``. Gaussians of the set (walls, the
    floor itself, rigging beyond the stage) fall outside it; the performers and what stands on the
    stage fall inside."""
    sx, sy, sz = (float(v) for v in stage_size_m)
    return (-sx / 2, -sy / 2, floor_clearance_m), (sx / 2, sy / 2, sz)
