import pyarrow as pa

# DESIGN §6 minimum columns for `measurements`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('point_id', pa.int64()),
    pa.field('x_mm', pa.float64()),
    pa.field('y_mm', pa.float64()),
    pa.field('z_mm', pa.float64()),
    pa.field('nx', pa.float64()),
    pa.field('ny', pa.float64()),
    pa.field('nz', pa.float64()),
    pa.field('err_um', pa.float64()),
    pa.field('t_s', pa.float64()),
])
