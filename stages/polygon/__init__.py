"""Polygon (2-axis) cutting, seed 004 (JP2015-043126): a bar turning at ω1 and a fly cutter on an
eccentric parallel axis at ω2 leave a blade, a lens or a p-gon, twisted along the axis.

- ``kinematics``: the edge tip in the workpiece-fixed frame, the cut one edge passage leaves
  (a fine profile over the unwrapped polar angle) and the passages (events) that machine a z range;
- ``cut``: the radial height map r(θ, z) of the machined solid, chunk by chunk in z;
- ``sections``: sides, face orientation and twist, caliper thickness of cross-sections;
- ``mesh``: the solid as a closed triangle mesh (STL);
- ``pictures``: cross-sections and a 3-D view (matplotlib, Agg).

Conventions (docs/polygon.md): ω > 0 is counter-clockwise seen from +z; the cutter's axis sits at
(ε, 0) of the fixed frame; the edge advances along +z; an edge's lag is the cutter rotation by
which it follows the first edge; θ and z are in the workpiece-fixed frame.
"""
from stages.polygon.kinematics import Setup, ratio_fraction, tip_xy

__all__ = ["Setup", "ratio_fraction", "tip_xy"]
