import pyarrow as pa

# DESIGN §6 minimum columns for `corrected`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('block_no', pa.int32()),
    pa.field('x_mm', pa.float64()),
    pa.field('y_mm', pa.float64()),
    pa.field('z_mm', pa.float64()),
    pa.field('x_new_mm', pa.float64()),
    pa.field('y_new_mm', pa.float64()),
    pa.field('z_new_mm', pa.float64()),
])
