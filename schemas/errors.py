import pyarrow as pa

# DESIGN §6 minimum columns for `errors`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('err_deflection_um', pa.float64()),
    pa.field('err_shape_um', pa.float64()),
    pa.field('err_um', pa.float64()),
    pa.field('nx', pa.float64()),
    pa.field('ny', pa.float64()),
    pa.field('nz', pa.float64()),
])
