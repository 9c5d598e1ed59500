import pyarrow as pa

from schemas import surface_point

# DESIGN §6 minimum columns for `measurements`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('point_id', pa.int64()),
    *surface_point(),
    pa.field('err_um', pa.float64()),
    pa.field('t_s', pa.float64()),
])
