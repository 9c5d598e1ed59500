import pyarrow as pa

# DESIGN §6 minimum columns for `cut_filter`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('is_cutting', pa.bool_()),
    pa.field('cut_px', pa.int32()),
    pa.field('pred_x_mm', pa.float64()),
    pa.field('pred_y_mm', pa.float64()),
    pa.field('pred_z_mm', pa.float64()),
])
