import pyarrow as pa

# One row per NC program. status: ok | failed. message: "file:line: what and why" when failed.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("path", pa.string(), nullable=False),       # the program file, relative to the workflow
    pa.field("sha256", pa.string(), nullable=False),
    pa.field("tool", pa.int32()),             # T number of the cutter (null when none was called)
    pa.field("n_lines", pa.int32(), nullable=False),
    pa.field("n_blocks", pa.int32(), nullable=False),
    pa.field("n_passes", pa.int32(), nullable=False),
    pa.field("cut_length_mm", pa.float64(), nullable=False),
    pa.field("duration_s", pa.float64(), nullable=False),
    pa.field("status", pa.string(), nullable=False),
    pa.field("message", pa.string(), nullable=False),
])
