import pyarrow as pa

# Scheduled feed per pass (stage `feed`, only with a `feed:` section): one row per pass of the
# program. The feed keeps the predicted peak deflection within feed.max_deflection_um and the
# feed per tooth (the largest chip) within feed.max_chip_mm, between feed.min_mm_min and
# feed.max_mm_min, neighbours within feed.max_change.
SCHEMA = pa.schema([
    pa.field("program_id", pa.string(), nullable=False),
    pa.field("pass_id", pa.int32(), nullable=False),
    pa.field("line_no", pa.int32(), nullable=False),
    pa.field("feed_mm_min", pa.float64(), nullable=False),        # as programmed (rapids: the rapid rate)
    pa.field("feed_new_mm_min", pa.float64(), nullable=False),    # scheduled (rapids unchanged)
    pa.field("peak_deflection_um", pa.float64()),                 # at the programmed feed; null: not predicted
    pa.field("peak_deflection_new_um", pa.float64()),             # at the scheduled feed
    pa.field("chip_mm", pa.float64()),                            # feed per tooth, programmed
    pa.field("chip_new_mm", pa.float64()),                        # feed per tooth, scheduled
    # what set the feed: deflection | chip | max_feed | min_feed | smoothing | air (not cutting:
    # the maximum) | as_programmed (cutting, not predicted) | rapid
    pa.field("limited_by", pa.string(), nullable=False),
    pa.field("overloaded", pa.bool_(), nullable=False),           # over the deflection limit even at the minimum feed
    pa.field("duration_s", pa.float64(), nullable=False),         # the pass at the programmed feed
    pa.field("duration_new_s", pa.float64(), nullable=False),     # at the scheduled feed
])
