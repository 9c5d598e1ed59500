import pyarrow as pa

# DESIGN §6 `corrected`: one row per NC vertex (the end point of a G0–G3 block), written by the stage
# `correct` (seed 000 para 0084). x/y/z_mm: the ORIGINAL program's coordinates (program frame, mm,
# absolute); x/y/z_new_mm: after all rounds so far. Arcs carry their refitted centre (null for lines).
# With correct.via_points a long G1 line is several blocks (stages.nc_writer.via_blocks): its rows
# share the line_no, and every row but the line's last is a via point the writer may insert.
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('block_no', pa.int32()),
    pa.field('line_no', pa.int32()),          # 1-based line in the source file
    pa.field('motion', pa.int8()),            # 0 rapid, 1 linear, 2 cw arc, 3 ccw arc
    pa.field('x_mm', pa.float64()),
    pa.field('y_mm', pa.float64()),
    pa.field('z_mm', pa.float64()),
    pa.field('x_new_mm', pa.float64()),
    pa.field('y_new_mm', pa.float64()),
    pa.field('z_new_mm', pa.float64()),
    pa.field('cx_new_mm', pa.float64()),      # refitted arc centre (absolute), null for G0/G1
    pa.field('cy_new_mm', pa.float64()),
    pa.field('cz_new_mm', pa.float64()),
    pa.field('move_um', pa.float64()),        # |new − original|, all rounds
    pa.field('change_um', pa.float64()),      # |move| of the last round (iteration stops below tol_um)
    pa.field('clipped', pa.bool_()),          # the move was limited to correct.max_move_um
    pa.field('gouge_limit_um', pa.float64()), # taken off the move so the tool stays off the surface
                                              # other passes generate (stages.correct.gouge_limit;)
    pa.field('iteration', pa.int32()),        # rounds of predict → correct run so far
    pa.field('relax', pa.float64()),          # fraction of its step the vertex took in the last round
    pa.field('step_x_um', pa.float64()),      # the step the last round's errors asked for (before the
    pa.field('step_y_um', pa.float64()),      # fraction, the clip and arc refits): the next round's
    pa.field('step_z_um', pa.float64()),
    pa.field('nx', pa.float64()),             # vertex normal (unit sum of the predicted passes' normals),
    pa.field('ny', pa.float64()),             # NaN where no predicted pass meets the vertex
    pa.field('nz', pa.float64()),
    # thermal drift compensation (workflow section drift): minus the drift predicted when the tool
    # reaches the vertex, µm; 0 without it. x/y/z_new_mm stay the error correction (the rounds
    # predict on the path the tool follows in the workpiece frame, where drift and compensation
    # cancel); the writers write x/y/z_new_mm + drift (stages.thermal.compensate.with_drift)
    pa.field('drift_x_um', pa.float64()),
    pa.field('drift_y_um', pa.float64()),
    pa.field('drift_z_um', pa.float64()),
])
