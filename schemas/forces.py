import pyarrow as pa

# DESIGN §6 minimum columns for `forces`; the stage that fills it may add more here.
# Forces act on the tool, machine frame, sampled at spindle angles rotation_deg (θ = 0: flute 0's
# tip end along the feed direction; spindle clockwise seen from above, see stages/cutting.py).
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('rotation_deg', pa.list_(pa.float64())),
    pa.field('fx_n', pa.list_(pa.float64())),
    pa.field('fy_n', pa.list_(pa.float64())),
    pa.field('fz_n', pa.list_(pa.float64())),
    pa.field('spindle_rpm', pa.float64()),         # period of the force: 60/spindle_rpm s
    pa.field('feed_per_tooth_mm', pa.float64()),   # fz = F/(S·flutes)
])
