import pyarrow as pa

# DESIGN §6 minimum columns for `generating`; the stage that fills it may add more here.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('gen_x_mm', pa.float64()),
    pa.field('gen_y_mm', pa.float64()),
    pa.field('gen_z_mm', pa.float64()),
    pa.field('rotation_deg', pa.float64()),
    pa.field('contact_deg', pa.float64()),
    pa.field('nx', pa.float64()),
    pa.field('ny', pa.float64()),
    pa.field('nz', pa.float64()),
    pa.field('n_px', pa.int32()),       # strip points of the tool at the prediction point that survive
    pa.field('view', pa.string()),       # "strip": found on the tool's strip; "none": the pass leaves no surface
    # a second contact of the pass with the design surface (a ball in a vertical corner finishes
    # both walls, one on a floor beside a wall its foot): NaN and 0 where there is none
    pa.field('gen2_x_mm', pa.float64()),
    pa.field('gen2_y_mm', pa.float64()),
    pa.field('gen2_z_mm', pa.float64()),
    pa.field('rotation2_deg', pa.float64()),
    pa.field('contact2_deg', pa.float64()),
    pa.field('nx2', pa.float64()),
    pa.field('ny2', pa.float64()),
    pa.field('nz2', pa.float64()),
    pa.field('n2_px', pa.int32()),
])
