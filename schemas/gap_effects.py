import pyarrow as pa

# DESIGN §6 minimum columns for `gap_effects`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('effect', pa.string()),
    pa.field('params', pa.string()),
    pa.field('rms_before_um', pa.float64()),
    pa.field('rms_after_um', pa.float64()),
    pa.field('explained', pa.float64()),
    pa.field('rank', pa.int32()),
])
