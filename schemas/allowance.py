import pyarrow as pa

# The stock each predicted pass meets along the surface normal from its generating point (stage
# `warn`, stages/surface/allowance.py): the finishing allowance, or rest material.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("pass_id", pa.int32(), nullable=False),
    pa.field("stock_mm", pa.float64()),            # null: nothing engaged at the prediction point
])
