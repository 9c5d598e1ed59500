"""Which passes cut, and where (seed 000 claim 7, paras 0052-0054).

One ordered scan per tile (``Renderer.scan``), from below: the stock W first, then the sweep of
every pass in execution order with the depth test and depth writes, as the machine removes the
material. A fragment of pass k passes the depth test where its sweep is in front of W and of the
sweeps of all earlier passes T1 drawn before it: exactly claim 7's cutting region, for every pass
in one render instead of one window per pass. Per pass the scan counts those pixels by position
along the pass (``cut_px``), keeps their largest contact angle, and its final image is the
claim-8 render (which pass leaves which pixel of the final surface), used by ``angle_prune``.
A pass without a cut pixel is not cutting (air moves, passes inside already removed material);
rapid moves (motion 0) never cut.

The prediction point is the tool tip on the pass at the median position (along the pass, from
the pixels' own positions projected on the line of corner centres) of the cut pixels, preferring
the pass interior: it lies inside the cutting part even when the pass cuts only part of its
length. A pass inside a cutting run of one line (its neighbours cut and carry its line on) is
predicted at its middle (:func:`line_interior`).

Sweeps are drawn with a depth bias of ``tol`` (the polygonisation tolerance): a pass must cut
deeper than the meshes' own error into the stock to count, and a pass that repeats an earlier
one ties with it and does not count. Memory is bounded by the tile and the sweeps meshed per
draw, never by the program.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.passes import CONTINUE_DEG, PassGeometry
from stages.surface.ordered import N_BINS


def cut_columns(pg: PassGeometry, counts: np.ndarray, b_max: np.ndarray, surface_px: np.ndarray,
                surface_q: np.ndarray) -> dict:
    """The ``cut_filter`` columns of every pass from its scan statistics (claim 7).

    Returns a dict of numpy columns: is_cutting, cut_px, pred_x/y/z_mm, pred_t,
    cut_max_contact_deg (largest contact angle over the pixels the pass cuts), surface_px and
    surface_max_contact_deg (pixels of the final surface the pass leaves, their largest q).
    """
    n = len(pg.pass_id)
    cut_px = counts.sum(1)
    out = dict(is_cutting=cut_px > 0, cut_px=cut_px, pred_x_mm=np.full(n, np.nan),
               pred_y_mm=np.full(n, np.nan), pred_z_mm=np.full(n, np.nan), pred_t=np.full(n, np.nan),
               cut_max_contact_deg=np.where(cut_px > 0, b_max, np.nan),
               surface_px=surface_px,
               surface_max_contact_deg=np.where(surface_px > 0, surface_q, np.nan))
    cutting = np.nonzero(cut_px > 0)[0]
    t = prediction_position(counts[cutting])
    t[line_interior(pg, cut_px > 0)[cutting]] = 0.5
    p = pg.p0[cutting] + t[:, None] * (pg.p1[cutting] - pg.p0[cutting])
    out["pred_t"][cutting] = t
    out["pred_x_mm"][cutting], out["pred_y_mm"][cutting], out["pred_z_mm"][cutting] = p.T
    return out


def line_interior(pg: PassGeometry, cuts: np.ndarray) -> np.ndarray:
    """Passes inside a cutting run of one line, predicted at their middle (bool per pass).

    A pass counts when the moves before and after it both cut, are joined to it end to start and
    carry its direction on within :data:`CONTINUE_DEG` (pieces of a line split for
    length or at via points, a curve's CAM chords). Why: the ball at the end of the move before
    has already cut the material over most of such a pass's length, down to a sliver of
    d²/2R (12 µm at 0.5 mm past the joint with a Ø20 ball) that the coarse mesh tolerance (half a
    pixel) hides, so the pass's own cut pixels lie ahead of it, under the ball at its end, and
    their median put the prediction point at the end of the pass (the seed's cylinder cut into
    0.5 mm pieces: t = 0.97 on half of a level's pieces). The surface such a pass leaves is its
    whole length, each point where the tool's centre passes it; at its end the force is that of
    the next move's start, which at a stock edge (the cylinder's exit end, where the force falls
    by 20 % a piece) is another force than the pass's own.
    """
    n = len(pg.pass_id)
    inner = np.zeros(n, bool)
    if n < 3:
        return inner
    d = pg.p1 - pg.p0
    ln = np.linalg.norm(d, axis=1)
    u = d / np.where(ln > 0, ln, 1.0)[:, None]
    cos_on = np.cos(np.radians(CONTINUE_DEG))
    # joint i: move i ends where move i + 1 starts, both cut, and the direction runs on
    joint = (np.linalg.norm(pg.p0[1:] - pg.p1[:-1], axis=1) < 1e-6) & cuts[1:] & cuts[:-1] \
        & (ln[1:] > 0) & (ln[:-1] > 0) & (pg.motion[1:] != 0) & (pg.motion[:-1] != 0) \
        & (np.einsum("ij,ij->i", u[1:], u[:-1]) > cos_on)
    inner[1:-1] = joint[:-1] & joint[1:]
    return inner


def prediction_position(hist):
    """Median position along each pass of its cut pixels, preferring the pass interior.

    ``hist`` (k, N_BINS): cut pixels per bin of the position along the pass (pixels of the end
    copies count at 0 and 1). A point at a vertex lies where the path turns; the surface there
    is a fan that the neighbouring passes share, so the median over the bins within the middle
    60 % of the pass is used where they hold cut pixels (still a position where the pass cuts).
    """
    hist = np.asarray(hist, float).reshape(-1, N_BINS)
    centre = (np.arange(N_BINS) + 0.5) / N_BINS
    inner = (centre >= 0.2) & (centre <= 0.8)
    has_inner = hist[:, inner].sum(1, keepdims=True) > 0
    h = np.where(has_inner & inner[None], hist, np.where(has_inner, 0.0, hist))
    c = np.cumsum(h, 1)
    half = 0.5 * c[:, -1]
    k = np.argmax(c >= half[:, None], axis=1)
    rows = np.arange(len(h))
    before = c[rows, k] - h[rows, k]
    frac = (half - before) / np.maximum(h[rows, k], 1e-12)     # linear within the bin
    return (k + np.clip(frac, 0.0, 1.0)) / N_BINS
