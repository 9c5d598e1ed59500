import pyarrow as pa

# Tool wear per contact angle (issue 6 deliver 2): two profiles of the same tool (`pipeline
# tool-profile`, measured in a common frame) before and after a job, and the job's cutting length.
# One row per contact angle (0–90°, 0.1° steps, the profile grid). Written by `pipeline tool-wear`.
SCHEMA = pa.schema([
    pa.field('tool_id', pa.string(), nullable=False),         # user's name for the tool (default: after file stem)
    pa.field('contact_deg', pa.float64(), nullable=False),    # q, 0° at the tip, 90° at the equator
    pa.field('wear_um', pa.float64(), nullable=False),        # after − before of the contour error; > 0 = tool lost material
    pa.field('wear_rate_um_per_m', pa.float64()),             # wear_um / cut_length_m (null without a length)
    pa.field('cut_length_m', pa.float64()),                   # cutting length of the job between the two measurements
    pa.field('cut_length_source', pa.string(), nullable=False),  # "given" | "cut_filter" (cutting passes of a run) | "feed_moves" (run without cut_filter: every G1-G3 pass) | "none"
    pa.field('before_error_um', pa.float64(), nullable=False),   # the two profiles on the grid (error_um columns)
    pa.field('after_error_um', pa.float64(), nullable=False),
    pa.field('before_path', pa.string(), nullable=False),
    pa.field('after_path', pa.string(), nullable=False),
    pa.field('run', pa.string()),                             # run directory the length came from
    pa.field('programs', pa.list_(pa.string())),              # programs of the run that were counted
])
