import pyarrow as pa

# DESIGN §6 minimum columns for `angle_prune`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('max_contact_deg', pa.float64()),
    pa.field('predict', pa.bool_()),
])
