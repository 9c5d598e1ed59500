import pyarrow as pa

# Tool postures evaluated on a part (issue 61, seed 001 §4): one row per orientation of the grid.
# Written by `pipeline run` of a `job: posture` workflow. The tool axis θ points from the tip to the
# spindle; rx/ry and tilt/azimuth are the same axis in both spellings (docs/posture.md).
SCHEMA = pa.schema([
    pa.field('name', pa.string(), nullable=False),            # the workflow's name
    pa.field('orientation', pa.int32(), nullable=False),      # index in the grid (row-major over its two angles)
    pa.field('rx_deg', pa.float64(), nullable=False),         # θ = R_y(ry)·R_x(rx)·ẑ
    pa.field('ry_deg', pa.float64(), nullable=False),
    pa.field('tilt_deg', pa.float64(), nullable=False),       # angle of θ from +Z
    pa.field('azimuth_deg', pa.float64(), nullable=False),    # direction of the tilt from +X towards +Y (0 when vertical)
    pa.field('axis_x', pa.float64(), nullable=False),         # θ, unit vector
    pa.field('axis_y', pa.float64(), nullable=False),
    pa.field('axis_z', pa.float64(), nullable=False),
    pa.field('phi1', pa.float64(), nullable=False),           # eq. 3: area-weighted mean λ over the machinable region (0 if none)
    pa.field('phi2', pa.float64(), nullable=False),           # eq. 4: machinable area / total area
    pa.field('e', pa.float64(), nullable=False),              # eq. 5: (1 − α)·phi1 + α·phi2
    pa.field('machinable_area_mm2', pa.float64(), nullable=False),
])
