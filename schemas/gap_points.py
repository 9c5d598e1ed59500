import pyarrow as pa

# DESIGN §6 minimum columns for `gap_points`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('point_id', pa.int64()),
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('predicted_um', pa.float64()),
    pa.field('measured_um', pa.float64()),
    pa.field('residual_um', pa.float64()),
])
