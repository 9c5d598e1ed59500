"""Correction of NC programs against predicted or measured errors: vertex moves (:mod:`.moves`),\narc refits (:mod:`.arcs`) and the rounds (:mod:`.rounds`)."""
