"""Sim-to-real gap diagnosis (DESIGN §8, issue 7): where, which effect, how far, and the blind check.

Plain functions over numpy arrays. The measured points become a features dict ``F`` of (n,) arrays
(``associate.associate``); every later step reads it.

| module | what |
|---|---|
| ``measurements`` | reading a CMM export or Parquet file (``InputError`` naming file and line), writing one |
| ``associate`` | point → pass association, features, the prediction at the points (deepest tooth passage) |
| ``effects`` | the effect catalogue: signatures, parameters, physical limits and the fits' bounds |
| ``observability`` | what the plan observes: amplitudes held at nominal, nonlinear values not pinned |
| ``plans`` | plan kinds (full, floors, sections, walls); measured/rejected counts per band and direction |
| ``servo`` | the servo lag as the envelope of discrete tooth passages near corners |
| ``fit`` | grid and joint fits, spatial blocks and folds, held-out prediction, noise |
| ``collinearity`` | an effect next to others: its own contribution, canonical correlation, the size test |
| ``diagnose`` | the selection loop (greedy, swap, backward check) and the "where" blocks |
| ``uncertainty`` | the final joint fit, standard errors, detection limits, ambiguity |
| ``calibration`` | a reference part: force scale, corner floor, model floor as the baseline |
| ``predictor`` | "how far": the effects added to the prediction itself and re-run (``Predictor``) |
| ``tables``, ``report`` | ``gap_points`` / ``gap_effects`` tables; summary and HTML report |
| ``probe``, ``cases``, ``blind`` | measurements made on the virtual machine; the blind check's cases and scores |

The engine-side jobs (running the workflow, reading its measurement spec, writing files) are
``pipeline.gap_jobs``.
"""
