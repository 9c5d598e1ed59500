import pyarrow as pa

from schemas import endpoints

# One row per linear move after splitting (DESIGN §6). pass_id: execution order, 0-based.
# motion as in blocks: 0 rapid, 1 linear, 2 arc cw chord, 3 arc ccw chord.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("pass_id", pa.int32(), nullable=False),
    pa.field("block_no", pa.int32(), nullable=False),   # first NC block of the pass
    pa.field("block_end", pa.int32(), nullable=False),  # last NC block (passes merge short moves)
    pa.field("line_no", pa.int32(), nullable=False),
    pa.field("motion", pa.int8(), nullable=False),
    *endpoints(),
    pa.field("feed_mm_min", pa.float64(), nullable=False),  # rapid rate for G0
    pa.field("spindle_rpm", pa.float64(), nullable=False),
    pa.field("tool", pa.int32()),
    pa.field("t_start_s", pa.float64(), nullable=False),
    pa.field("t_end_s", pa.float64(), nullable=False),
])
