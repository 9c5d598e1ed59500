import pyarrow as pa

# DESIGN §6 minimum columns for `deflection`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('rotation_deg', pa.list_(pa.float64())),
    pa.field('dx_um', pa.list_(pa.float64())),
    pa.field('dy_um', pa.list_(pa.float64())),
])
