import pyarrow as pa

# The greedy union of postures (issue 61, seed 001 §6, eq. 6): one row per chosen posture, in the
# order chosen (each adds the most area not yet covered), until the union reaches the upper bound
# (the union over the whole grid) or cover.max_postures. Written by a `job: posture` run.
SCHEMA = pa.schema([
    pa.field('name', pa.string(), nullable=False),            # the workflow's name
    pa.field('step', pa.int32(), nullable=False),             # 1, 2, … in the order chosen
    pa.field('orientation', pa.int32(), nullable=False),      # row of table posture
    pa.field('rx_deg', pa.float64(), nullable=False),
    pa.field('ry_deg', pa.float64(), nullable=False),
    pa.field('tilt_deg', pa.float64(), nullable=False),
    pa.field('azimuth_deg', pa.float64(), nullable=False),
    pa.field('e', pa.float64(), nullable=False),              # E of the posture alone
    pa.field('added_area_mm2', pa.float64(), nullable=False),     # area this posture adds to the union
    pa.field('covered_area_mm2', pa.float64(), nullable=False),   # area of the union so far
    pa.field('covered_fraction', pa.float64(), nullable=False),   # covered_area_mm2 / upper_bound_mm2
    pa.field('upper_bound_mm2', pa.float64(), nullable=False),    # area machinable by some orientation of the grid
    pa.field('total_area_mm2', pa.float64(), nullable=False),     # area of the required surface
])
