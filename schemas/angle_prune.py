import pyarrow as pa

# DESIGN §6 `angle_prune` (claim 8), one row per pass. Added columns:
#   surface_px   pixels of the final-surface render (all sweeps, from below) won by the pass
#   source       where max_contact_deg comes from: "surface" (final-surface render), "cut" (the
#                pass's cut region, when its surface is not visible from below, e.g. steep
#                walls), "none" (not cutting)
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('max_contact_deg', pa.float64()),
    pa.field('predict', pa.bool_()),
    pa.field('surface_px', pa.int32()),
    pa.field('source', pa.string()),
])
