"""Measurement plans as real inspection programs make them (issue 59): the points of a full plan
that a floors-only, sections-only or walls-only program would probe, and what a plan measured and
rejected per contact-angle band and normal direction.
"""
from __future__ import annotations

import numpy as np

from stages import InputError

PLAN_KINDS = ("full", "floors", "sections", "walls")
FLOOR_DEG = 5.0          # a floor: normal within 5° of +z
WALL_DEG = 60.0          # a wall: normal at least 60° from +z
SECTIONS = 3             # sections: this many planes across the part's longest horizontal extent
SECTION_HALF_MM = 0.3    # points within this distance of a section plane
BANDS_DEG = (0.0, 5.0, 15.0, 30.0, 45.0, 60.0, 90.0)
MIN_POINTS = 30


def contact_deg(nrm: np.ndarray) -> np.ndarray:
    """Angle of each normal from +z (deg): (n, 3) unit normals → (n,)."""
    return np.degrees(np.arccos(np.clip(np.asarray(nrm, float)[:, 2], -1.0, 1.0)))


def plan_mask(pts: np.ndarray, nrm: np.ndarray, kind: str) -> np.ndarray:
    """The points of a full plan that a ``kind`` inspection program probes.

    Parameters
    ----------
    pts, nrm : (n, 3) ndarray
        Points (mm) and unit normals of the full plan.
    kind : str
        ``full``; ``floors`` (normal within ``FLOOR_DEG`` of +z); ``walls`` (at least ``WALL_DEG``
        from +z); ``sections`` (within ``SECTION_HALF_MM`` of ``SECTIONS`` planes square to the
        longest horizontal extent, at its quarter points).

    Returns
    -------
    (n,) bool ndarray

    Raises
    ------
    InputError
        Unknown kind, or fewer than ``MIN_POINTS`` points of that kind on the part.
    """
    if kind not in PLAN_KINDS:
        raise InputError(f"--plan-kind {kind!r}: unknown (known: {', '.join(PLAN_KINDS)})")
    q = contact_deg(nrm)
    if kind == "full":
        m = np.ones(len(q), bool)
    elif kind == "floors":
        m = q <= FLOOR_DEG
    elif kind == "walls":
        m = q >= WALL_DEG
    else:
        ext = np.ptp(pts[:, :2], axis=0)
        ax = int(np.argmax(ext))
        lo = pts[:, ax].min()
        planes = lo + ext[ax] * np.arange(1, SECTIONS + 1) / (SECTIONS + 1)
        m = np.min(np.abs(pts[:, ax, None] - planes[None]), axis=1) <= SECTION_HALF_MM
    if m.sum() < MIN_POINTS:
        raise InputError(f"--plan-kind {kind}: {int(m.sum())} of the plan's {len(q)} points are of that kind "
                         f"(at least {MIN_POINTS} needed; contact angles {q.min():.1f}–{q.max():.1f}°)")
    return m


def direction_of(nrm: np.ndarray) -> np.ndarray:
    """Each normal's dominant direction as text: ``+z``, ``-x`` … (n,) str."""
    nrm = np.asarray(nrm, float)
    ax = np.argmax(np.abs(nrm), axis=1)
    sign = np.where(nrm[np.arange(len(nrm)), ax] >= 0, "+", "-")
    return np.char.add(sign, np.array(["x", "y", "z"])[ax])


def plan_counts(nrm_measured: np.ndarray, nrm_rejected: np.ndarray, reasons=()) -> dict:
    """Measured and rejected points per contact-angle band and normal direction, with a warning when
    the rejected points are systematically one kind.

    Parameters
    ----------
    nrm_measured, nrm_rejected : (n, 3), (m, 3) ndarray
        Unit normals of the points used and of those rejected (m may be 0).
    reasons : sequence of str
        The rejection reason of each rejected point (the most common is named in a warning).

    Returns
    -------
    dict
        ``bands``: [{"band_deg": [lo, hi], "measured", "rejected"}] (bands with any point),
        ``directions``: [{"direction", "measured", "rejected"}], ``warnings``: [str].
    """
    nm = np.asarray(nrm_measured, float).reshape(-1, 3)
    nr = np.asarray(nrm_rejected, float).reshape(-1, 3)
    qm, qr = contact_deg(nm), contact_deg(nr)
    edges = np.array(BANDS_DEG)
    bm = np.clip(np.searchsorted(edges, qm, side="right") - 1, 0, len(edges) - 2)
    br = np.clip(np.searchsorted(edges, qr, side="right") - 1, 0, len(edges) - 2)
    bands = [{"band_deg": [float(edges[i]), float(edges[i + 1])], "measured": int(np.sum(bm == i)),
              "rejected": int(np.sum(br == i))} for i in range(len(edges) - 1) if np.any(bm == i) or np.any(br == i)]
    dm, dr = direction_of(nm), direction_of(nr)
    dirs = [{"direction": d, "measured": int(np.sum(dm == d)), "rejected": int(np.sum(dr == d))}
            for d in sorted(set(dm.tolist()) | set(dr.tolist()))]
    warnings = []
    why = ""
    if len(reasons):
        vals, cnt = np.unique(np.asarray(reasons, str), return_counts=True)
        why = f" (most often: {vals[np.argmax(cnt)]})"
    # systematic: the groups that lost at least half their points, together at 3× the rate of the others
    for rows, key in ((bands, "band_deg"), (dirs, "direction")):
        bad = [r for r in rows if r["rejected"] and r["rejected"] >= 0.5 * (r["measured"] + r["rejected"])]
        good = [r for r in rows if r not in bad]
        nb_r, nb = sum(r["rejected"] for r in bad), sum(r["measured"] + r["rejected"] for r in bad)
        ng_r, ng = sum(r["rejected"] for r in good), sum(r["measured"] + r["rejected"] for r in good)
        if bad and nb_r >= 5 and nb_r / nb >= 3 * ng_r / max(ng, 1):
            what = (f"contact angle {min(r[key][0] for r in bad):g}–{max(r[key][1] for r in bad):g}°" if key == "band_deg"
                    else "normal " + ", ".join(r[key] for r in bad))
            nb, nt = sum(r["rejected"] for r in bad), sum(r["measured"] + r["rejected"] for r in bad)
            warnings.append(f"{nb} of the {nt} points with {what} were rejected{why}: the diagnosis sees that kind "
                            f"of surface through {nt - nb} points only")
    return {"bands": bands, "directions": dirs, "warnings": warnings}
