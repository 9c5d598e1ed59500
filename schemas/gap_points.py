import pyarrow as pa

from schemas import surface_point

# DESIGN §6 `gap_points`: one row per measured point, with the features of the diagnosis (stages/gap/tables.py).
SCHEMA = pa.schema([
    pa.field('point_id', pa.int64()),
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('predicted_um', pa.float64()),
    pa.field('measured_um', pa.float64()),
    pa.field('residual_um', pa.float64()),
    *surface_point(),
    pa.field('q_deg', pa.float64()),               # contact angle
    pa.field('phi_deg', pa.float64()),             # rotation angle from the feed direction
    pa.field('t_s', pa.float64()),                 # machining time at the point
    pa.field('cut_len_mm', pa.float64()),          # cutting length so far
    pa.field('corner_dist_mm', pa.float64()),      # path distance to the nearest corner (inf: none)
    pa.field('corner_deg', pa.float64()),
    pa.field('feed_mm_min', pa.float64()),
    pa.field('pred_deflection_um', pa.float64()),
    pa.field('dist_mm', pa.float64()),             # distance from the tool envelope of the pass
    pa.field('residual_after_um', pa.float64()),   # held-out residual with the chosen effects added
])
