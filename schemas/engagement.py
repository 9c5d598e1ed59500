import pyarrow as pa

# One row per predicted pass: where the tool envelope is inside the material at the prediction
# point (seed 000 claim 5), on a grid of axial levels z_k = (k + 0.5) * dz_mm above the tool tip
# and rotation angles phi_j = (j + 0.5) * 360 / n_phi degrees, counter-clockwise from the feed
# direction seen from above. mask = np.packbits of the boolean array E (n_z, n_phi), C order;
# decode with stages.generating.unpack_engagement(row). feed_dir_x/y: unit horizontal feed direction;
# ramp_deg: angle of the feed above the horizontal (+ climbing, - descending), which sets the chip;
# chip_limit_mm: for a descending pass, quantiles over the engaged cells of the largest chip the
# material ahead allows (its thickness over the envelope / sin of the descent: a plunge into a thin
# cusp cuts only the cusp); the force takes the feed per tooth mean_i min(fz, L_i); null: level or climbing.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('dz_mm', pa.float64()),
    pa.field('n_z', pa.int32()),
    pa.field('n_phi', pa.int32()),
    pa.field('mask', pa.binary()),
    pa.field('feed_dir_x', pa.float64()),
    pa.field('feed_dir_y', pa.float64()),
    pa.field('ramp_deg', pa.float64()),
    pa.field('chip_limit_mm', pa.list_(pa.float64())),
])
