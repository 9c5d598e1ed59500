import pyarrow as pa

# Passes a correction cannot help (stage `warn`): one row per pass and reason.
#   beyond_move_limit  |err_um| larger than correct.max_move_um (value: err_um, µm)
#   rest_material      stock along the normal over warnings.rest_factor × the allowance (value: mm)
#   overloaded         deflection over feed.max_deflection_um even at feed.min_mm_min (value: µm)
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("pass_id", pa.int32(), nullable=False),
    pa.field("line_no", pa.int32(), nullable=False),
    pa.field("reason", pa.string(), nullable=False),
    pa.field("value", pa.float64(), nullable=False),
    pa.field("limit", pa.float64(), nullable=False),
    pa.field("message", pa.string(), nullable=False),
])
