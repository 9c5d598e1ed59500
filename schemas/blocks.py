import pyarrow as pa

from schemas import endpoints

# One row per motion block after modal state is resolved (intermediate table between parse and
# split; also what the corrected-program writer maps coordinates back onto).
# motion: 0 rapid (G0), 1 linear (G1), 2 arc cw (G2), 3 arc ccw (G3), 4 dwell (G4).
# plane: 17 | 18 | 19. Arc centre absolute, mm. Coordinates absolute, mm, machine frame.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("block_no", pa.int32(), nullable=False),   # ordinal of the block in the program, 1-based
    pa.field("line_no", pa.int32(), nullable=False),    # 1-based line in the file
    pa.field("n_number", pa.int32()),                    # the N word, when the block has one
    pa.field("motion", pa.int8(), nullable=False),
    pa.field("plane", pa.int16(), nullable=False),
    *endpoints(),
    pa.field("cx_mm", pa.float64()),
    pa.field("cy_mm", pa.float64()),
    pa.field("cz_mm", pa.float64()),
    pa.field("feed_mm_min", pa.float64()),
    pa.field("spindle_rpm", pa.float64(), nullable=False),
    pa.field("tool", pa.int32()),
    pa.field("inch", pa.bool_(), nullable=False),        # block was written in G20 (values converted)
    pa.field("incremental", pa.bool_(), nullable=False), # block was written in G91
    pa.field("dwell_s", pa.float64(), nullable=False),   # G4 blocks (motion 4): dwell time
    # the block's end is a via point inside a pass (correct.corner_via_mm): a cut of its line that
    # the split stage does not make, so the blocks on either side are one pass
    pa.field("via_only", pa.bool_(), nullable=False),
])
