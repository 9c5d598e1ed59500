import pyarrow as pa

# One row per program from the parse stage; split completes it into the `programs` table.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("path", pa.string(), nullable=False),
    pa.field("sha256", pa.string(), nullable=False),
    pa.field("tool", pa.int32()),
    pa.field("n_lines", pa.int32(), nullable=False),
    pa.field("n_blocks", pa.int32(), nullable=False),
    pa.field("status", pa.string(), nullable=False),
    pa.field("message", pa.string(), nullable=False),
])
