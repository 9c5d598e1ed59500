"""Cutting physics: mechanistic forces (:mod:`.forces`), compliance and deflection (:mod:`.frf`),
the tooth passages that finish a point (:mod:`.passages`), the error they leave
(:mod:`.surface_error`) and the calibration of the force coefficients (:mod:`.calibrate`)."""
