import pyarrow as pa

# DESIGN §6 `gap_effects`: one row per candidate effect, ranked on held-out blocks (stages/gap/tables.py).
SCHEMA = pa.schema([
    pa.field('effect', pa.string()),
    pa.field('params', pa.string()),               # JSON of the fitted parameters (chosen effects)
    pa.field('params_se', pa.string()),            # JSON: standard error of each (null: not identifiable)
    pa.field('rms_before_um', pa.float64()),
    pa.field('rms_after_um', pa.float64()),        # held-out, this effect alone
    pa.field('explained', pa.float64()),
    pa.field('rank', pa.int32()),
    pa.field('gain_sigma2', pa.float64()),         # held-out SSE improvement / noise variance
    pa.field('threshold_sigma2', pa.float64()),    # χ² quantile it must beat
    pa.field('chosen', pa.bool_()),
    pa.field('hidden_up_to_um', pa.float64()),     # not chosen: largest RMS of it that would not be claimed
    pa.field('ambiguous_with', pa.string()),       # chosen: JSON list of effects it cannot be told from here
    pa.field('not_observable', pa.string()),       # JSON {parameter: reason}: not determined by these points (held at nominal)
    pa.field('possible', pa.string()),             # why it is possible, not claimed (null: claimed or not chosen)
])
