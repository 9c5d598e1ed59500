"""How far (DESIGN §8 step 4): the chosen effects added to the simulation itself, and the prediction
run again, on held-out points.

The model effects (force scale, runout, tool profile) re-run the pipeline's own prediction
downstream of the render (forces → deflection → errors at the measured points: ``Predictor``); the
others are added as their term along the normal.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import pyarrow as pa

from stages import deflection as deflection_stage
from stages import errors as errors_stage
from stages import forces as forces_stage
from stages.gap.associate import predicted_at_points
from stages.gap.diagnose import diagnose, where
from stages.gap.model_update import profile_values
from stages.gap.fit import fold_fits, rms, shrink_where_acting
from stages.gap.unexplained import SHRINK_CLAIM, unexplained
from stages.geometry.cutter import Cutter

COEFFS = ("ktc", "krc", "kac", "kte", "kre", "kae")
RUNOUT_GRID_UM = (1.0, 2.0, 4.0, 7.0, 11.0, 16.0, 24.0)   # runout values the prediction is re-run at
# how each catalogue effect is added to the simulation for "how far"
HOW_ADDED = {
    "force_scale": "re-predicted: material ktc…kae × scale, forces → deflection → errors re-run",
    "runout": "re-predicted: tool.runout_um + e (flute 0 largest; the prediction has no runout phase), "
              "forces → deflection → errors re-run",
    "tool_contour": "re-predicted: tool.profile table (contact_deg, error_um) of the fitted dent, errors re-run",
}
OFFSET_ADDED = "term along the normal added to the prediction (the machine/tool offset model)"


class Predictor:
    """The pipeline's own prediction downstream of the render, re-run with changed parameters.

    The cached ``generating`` and ``engagement`` tables are reused; ``stages.forces.run`` →
    ``stages.deflection.run`` (→ ``stages.errors.machining_error`` at the measured points, the
    errors stage's kernel) are called directly, once per program and parameter set (cached here).
    ``scale`` is the baseline force-model scale (a reference-part calibration; 1 without one).

    Parameters
    ----------
    tabs : dict
        The run's tables ({name: pa.Table}: ``passes``, ``generating``, ``engagement``).
    tool, material, machine : dict
        The workflow's entries (as the stages take them).
    scale : float
        Baseline force-model scale (ratio).
    workdir : Path, optional
        Where fitted tool-profile tables are written (a temporary directory when None).
    """

    def __init__(self, tabs: dict, tool: dict, material: dict, machine: dict, scale: float = 1.0,
                 workdir: Optional[Path] = None):
        self.tabs = tabs
        self.tool, self.material, self.machine = dict(tool), dict(material), machine
        self.scale = float(scale)
        self.workdir = Path(workdir) if workdir else None
        self._defl: dict = {}
        self._n_profiles = 0

    def _deflection(self, prog: str, scale: float, runout_um: float) -> pa.Table:
        key = (prog, round(scale, 9), round(runout_um, 6))
        if key not in self._defl:
            pick = lambda t: t.filter(pa.compute.equal(t.column("program_id"), prog))  # noqa: E731
            tool = dict(self.tool, runout_um=runout_um)
            mat = {k: (float(v) * scale if k in COEFFS and v is not None else v) for k, v in self.material.items()}
            f = forces_stage.run({"passes": pick(self.tabs["passes"]), "generating": pick(self.tabs["generating"]),
                         "engagement": pick(self.tabs["engagement"])}, {"tool": tool, "material": mat})["forces"]
            self._defl[key] = deflection_stage.run({"forces": f}, {"machine": self.machine, "tool": tool})["deflection"]
            if len(self._defl) > 64:
                self._defl.pop(next(iter(self._defl)))
        return self._defl[key]

    def profile_csv(self, contour: dict, name: Optional[str] = None) -> str:
        """A tool profile table (claim 2, ``contact_deg,error_um``) with the fitted dent added to the
        workflow's profile, written where ``tool.profile`` can point at it.

        Parameters
        ----------
        contour : dict
            ``a_um`` (µm), ``q0_deg``, ``width_deg`` (deg).
        name : str, optional
            File name in ``workdir``.

        Returns
        -------
        str
            Path of the CSV.
        """
        q = np.round(np.arange(0.0, 90.0 + 1e-9, 0.25), 6)
        e = profile_values(q, Cutter.from_params(self.tool).profile, contour, 0.0)
        if self.workdir is None:
            import tempfile
            self.workdir = Path(tempfile.mkdtemp(prefix="gap_"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._n_profiles += 1
        path = self.workdir / (name or f"tool_profile_fitted_{self._n_profiles}.csv")
        path.write_text("contact_deg,error_um\n" + "".join(f"{a:.4f},{b:.6f}\n" for a, b in zip(q, e)))
        return str(path)

    def tool_for(self, params: dict) -> tuple[dict, float]:
        """(tool, force scale) of the prediction with the model effects in ``params`` added.

        Parameters
        ----------
        params : dict
            {effect: reported parameters}; ``force_scale``, ``runout`` and ``tool_contour`` act.

        Returns
        -------
        tool : dict
            The tool entry with ``runout_um`` and ``profile`` changed.
        scale : float
            The force-model scale (baseline × fitted).
        """
        tool = dict(self.tool)
        if "runout" in params:
            base = Cutter.from_params(self.tool).runout_um
            tool["runout_um"] = base + max(float(params["runout"]["e_um"]), 0.0)
        if "tool_contour" in params:
            tool["profile"] = params["tool_contour"].get("profile_csv") or self.profile_csv(params["tool_contour"])
        scale = self.scale * float(params.get("force_scale", {}).get("scale", 1.0))
        return tool, scale

    def at_points(self, F: dict, params: dict, rows: Optional[np.ndarray] = None, runout_part: bool = False) -> np.ndarray:
        """Predicted error (µm) at the measured points ``rows`` with the model effects ``params``
        (force_scale, runout, tool_contour; others are ignored) added to the simulation (with
        ``runout_part``: its runout part −ρ·sin q alone).

        Parameters
        ----------
        F : dict
            Features of n points (``stages.gap.associate.associate``, with the passage geometry).
        params : dict
            {effect: reported parameters}.
        rows : (n,) bool ndarray, optional
            The points (all when None).
        runout_part : bool

        Returns
        -------
        (m,) ndarray
            µm along each normal at the m selected points.
        """
        tool, scale = self.tool_for(params)
        runout = Cutter.from_params(tool).runout_um
        # each point's own pass and the neighbouring passes' tooth passages that sweep it
        return predicted_at_points(F, lambda prog: self._deflection(prog, scale, runout), tool, rows, runout_part)[0]

    def errors_table(self, params: dict) -> pa.Table:
        """The ``errors`` table (pa.Table) re-predicted with the model effects in ``params``
        ({effect: reported parameters}) added: the errors stage re-run."""
        tool, scale = self.tool_for(params)
        out = []
        for prog in dict.fromkeys(self.tabs["passes"].column("program_id").to_pylist()):
            pick = lambda t: t.filter(pa.compute.equal(t.column("program_id"), prog))  # noqa: E731
            d = self._deflection(prog, scale, Cutter.from_params(tool).runout_um)
            out.append(errors_stage.run({"passes": pick(self.tabs["passes"]), "generating": pick(self.tabs["generating"]),
                                "deflection": d}, {"tool": tool})["errors"])
        return pa.concat_tables(out)


def add_model_responses(F: dict, predictor: Optional[Predictor]) -> dict:
    """The prediction's own response to runout on a grid of e (for the runout effect's signature).

    Parameters
    ----------
    F : dict
        Features of n points.
    predictor : Predictor or None
        None: ``F`` unchanged.

    Returns
    -------
    dict
        A copy of ``F`` with ``runout_grid_um`` (g,) µm and ``runout_resp_um`` (n, g, 2) µm: the
        flute's runout part and the rest of the change (``stages.gap.effects.runout_response``).
    """
    if predictor is None:
        return F
    F = dict(F)
    base, base_geo = predictor.at_points(F, {}), predictor.at_points(F, {}, runout_part=True)
    resp = np.zeros((len(base), len(RUNOUT_GRID_UM), 2))
    for i, e in enumerate(RUNOUT_GRID_UM):
        p = {"runout": {"e_um": e}}
        total = predictor.at_points(F, p) - base
        resp[:, i, 0] = predictor.at_points(F, p, runout_part=True) - base_geo
        resp[:, i, 1] = total - resp[:, i, 0]
    F["runout_grid_um"] = np.array(RUNOUT_GRID_UM)
    F["runout_resp_um"] = resp
    return F


def how_far(F: dict, res: dict, predictor: Optional[Predictor]) -> dict:
    """Held-out "after" with the chosen effects added to the simulation itself.

    Every spatial fold is predicted with the effects fitted without it: model effects
    (force_scale, runout, tool_contour) through the re-run prediction (``Predictor``), the others
    as their term along the normal. Replaces the "after" figures of ``res``; the after of the
    fitted terms alone is kept as ``rms_after_terms_um``.

    Parameters
    ----------
    F : dict
        Features of n points.
    res : dict
        ``stages.gap.diagnose.diagnose`` result (changed in place).
    predictor : Predictor or None

    Returns
    -------
    dict
        ``res`` with ``how_added``, ``rms_after_um``, ``p95_after_um``, ``max_after_um`` (µm),
        ``shrink``, ``shrink_where_acting``, ``rms_after_terms_um`` and ``_after`` (n,) µm.
    """
    chosen = res["_chosen"]
    res["how_added"] = {e.name: (HOW_ADDED[e.name] if predictor is not None and e.name in HOW_ADDED else OFFSET_ADDED
                                 if e.name not in HOW_ADDED else "term of the prediction model (no render tables to re-run)")
                        for e, _ in chosen}
    if not chosen:
        return res
    y, meas = F["residual_um"], F["measured_um"]
    after, terms_after = np.zeros_like(y), np.zeros_like(y)
    for test, items in fold_fits(F, y, res["_fold"], chosen):
        terms = np.zeros(int(test.sum()))
        offsets = np.zeros_like(terms)
        model = {}
        for e, th, b in items:
            c = e.basis(F, th)[test] @ b
            terms += c
            if predictor is not None and e.name in HOW_ADDED:
                model[e.name] = e.params(b, th)
            else:
                offsets += c
        pred = (predictor.at_points(F, model, test) + np.broadcast_to(F.get("baseline_extra_um", 0.0), y.shape)[test]
                if model else F["predicted_um"][test])
        after[test] = meas[test] - pred - offsets
        terms_after[test] = y[test] - terms
    res["rms_after_terms_um"] = rms(terms_after)
    res["rms_after_um"] = rms(after)
    res["p95_after_um"] = float(np.percentile(np.abs(after), 95))
    res["max_after_um"] = float(np.abs(after).max())
    res["shrink"] = float(1 - res["rms_after_um"] / res["rms_before_um"]) if res["rms_before_um"] > 0 else 0.0
    res["shrink_where_acting"] = shrink_where_acting(y, after, y - terms_after)
    res["_after"] = after
    return res


def diagnose_points(F: dict, sigma: Optional[float], floor_um: float = 0.0,
                    predictor: Optional[Predictor] = None) -> dict:
    """Diagnosis of associated points: the catalogue (with the prediction's own runout response when
    a ``predictor`` is given), then "how far" with the effects added to the simulation.

    Parameters
    ----------
    F : dict
        Features of n points (``stages.gap.associate.associate``; a baseline applied, if any).
    sigma : float, optional
        Probe noise σ (µm); estimated when None.
    floor_um : float
        The model's own floor (µm).
    predictor : Predictor, optional

    Returns
    -------
    dict
        The ``stages.gap.diagnose.diagnose`` result after ``how_far``, with ``where`` and
        ``where_after`` (``stages.gap.diagnose.where``).
    """
    F = add_model_responses(F, predictor)
    # one BLAS thread: the selection makes ~20,000 products of ≤ 20,000 × 10 matrices, which a
    # second thread does not speed up, and whose threads spin-wait for a time slice when another
    # job holds a core (100,000-point bench at load 2–3: 154–171 s with OpenBLAS's 2 threads, 30 s with one)
    with _one_blas_thread():
        res = diagnose(F, sigma, floor_um)
        res = how_far(F, res, predictor)
    answer_unexplained(F, res, floor_um)
    res["where"] = where(F, F["residual_um"], res["sigma_um"], res["_blocks"])
    res["where_after"] = where(F, res["_after"], res["sigma_um"], res["_blocks"])
    return res


def answer_unexplained(F: dict, res: dict, floor_um: float = 0.0) -> dict:
    """Structure the chosen effects leave (``stages.gap.unexplained``), scanned in the residual of
    their fit on all points (a held-out residual would also hold the misses of local effects on
    their own held-out blocks). When some is found and the chosen effects' held-out shrink is below
    ``SHRINK_CLAIM`` (they soak up part of an error outside the catalogue), the answer is
    "unexplained" and they are listed as possible, not claimed.

    Parameters
    ----------
    F : dict
    res : dict
        Result of ``how_far`` (changed in place: ``unexplained``, ``possible``, and when the answer is
        unexplained ``effect`` and ``effects``).
    floor_um : float

    Returns
    -------
    dict
        ``res``.
    """
    r = F["residual_um"] - sum(res["_contrib"].values(), np.zeros(len(F["residual_um"])))
    res["unexplained"] = unexplained(F, r, res["sigma_um"], floor_um)
    res.setdefault("possible", [])
    if res["unexplained"] is not None and (not res["effects"] or res["shrink"] < SHRINK_CLAIM):
        why = (f"took up part of structure the catalogue does not explain (held-out shrink {res['shrink']:.0%}, "
               f"under the {SHRINK_CLAIM:.0%} a claim needs next to it)")
        res["possible_why"] = {**{e: why for e in res["effects"]}, **res.get("possible_why", {})}
        res["possible"], res["effects"], res["effect"] = list(res["effects"]) + res["possible"], [], "unexplained"
    return res


def _one_blas_thread():
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:            # an environment installed before the dependency: run as before
        import contextlib
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")
