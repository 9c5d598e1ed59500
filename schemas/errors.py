import pyarrow as pa

# DESIGN §6 minimum columns for `errors`; the stage that fills it may add more here.
# err_um = err_deflection_um + err_runout_um + err_shape_um, positive = material left (DESIGN §5).
SCHEMA = pa.schema([
    pa.field('program_id', pa.string()),
    pa.field('pass_id', pa.int32()),
    pa.field('err_deflection_um', pa.float64()),   # (dx, dy, 0)(θ_C)·n
    pa.field('defl_x_um', pa.float64()),           # the tool's deflection (dx, dy, 0)(θ_C) of the
    pa.field('defl_y_um', pa.float64()),           # passage that leaves C, machine frame
    pa.field('err_shape_um', pa.float64()),        # tool profile table at contact_deg
    pa.field('err_um', pa.float64()),
    pa.field('nx', pa.float64()),
    pa.field('ny', pa.float64()),
    pa.field('nz', pa.float64()),
    pa.field('err_runout_um', pa.float64()),       # −ρ_flute·sin q of the generating flute
    pa.field('contact_deg', pa.float64()),         # q at the generating point C (of the finishing passage)
    pa.field('spindle_deg', pa.float64()),         # spindle angle θ_C at which deflection was read
    pa.field('flute', pa.int32()),                 # flute that generated C (the deepest cut)
    pa.field('finished_by', pa.int32()),           # pass whose tooth passage leaves C (the deepest; a
                                                   # neighbour near the ends of passes shorter than a revolution's feed)
    # the error at the pass's second contact with the design surface (generating's *2 columns: a
    # ball in a vertical corner, on a floor beside a wall); NaN where there is none
    pa.field('err2_um', pa.float64()),
    pa.field('nx2', pa.float64()),
    pa.field('ny2', pa.float64()),
    pa.field('nz2', pa.float64()),
    pa.field('contact2_deg', pa.float64()),
])
