import pyarrow as pa

# DESIGN §6 minimum columns for `generating`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('gen_x_mm', pa.float64()),
    pa.field('gen_y_mm', pa.float64()),
    pa.field('gen_z_mm', pa.float64()),
    pa.field('rotation_deg', pa.float64()),
    pa.field('contact_deg', pa.float64()),
    pa.field('nx', pa.float64()),
    pa.field('ny', pa.float64()),
    pa.field('nz', pa.float64()),
    pa.field('n_px', pa.int32()),
    pa.field('view', pa.string()),
])
