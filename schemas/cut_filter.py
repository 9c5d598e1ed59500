import pyarrow as pa

# DESIGN §6 `cut_filter` (claim 7), one row per pass. Added columns:
#   pred_t               position of the prediction point along the pass, 0..1 (NaN if not cutting)
#   cut_max_contact_deg  largest contact angle over the pixels the pass cuts (upper bound for the
#                        contact angle of the surface it leaves; used by angle_prune for passes
#                        whose surface is not visible from below)
#   surface_px           pixels of the final surface (all sweeps and the stock, from below) the
#                        pass leaves; surface_max_contact_deg their largest contact angle
#                        (the claim-8 render, a by-product of the ordered scan)
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('is_cutting', pa.bool_()),
    pa.field('cut_px', pa.int32()),
    pa.field('pred_x_mm', pa.float64()),
    pa.field('pred_y_mm', pa.float64()),
    pa.field('pred_z_mm', pa.float64()),
    pa.field('pred_t', pa.float64()),
    pa.field('cut_max_contact_deg', pa.float64()),
    pa.field('surface_px', pa.int32()),
    pa.field('surface_max_contact_deg', pa.float64()),
])
