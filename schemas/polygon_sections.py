import pyarrow as pa

# Cross-sections of the bar machined by the polygon job (seed 004, pipeline/polygon_job.py): the radius
# of the machined solid at each polar angle of the workpiece-fixed frame, at evenly spaced stations z.
SCHEMA = pa.schema([
    pa.field("z_mm", pa.float64(), nullable=False),       # along the axis, from the start of the cut
    pa.field("theta_deg", pa.float64(), nullable=False),  # counter-clockwise seen from +z, [0, 360)
    pa.field("r_mm", pa.float64(), nullable=False),       # at most the bar's radius (uncut)
])
