"""Evaluation of tool orientations (seed §4): Φ1, Φ2 and E = (1 − α) Φ1 + α Φ2 (eqs. 3–5).

Micro-regions are weighted by their area: Φ1 is the area-weighted mean λ over the machinable
region, Φ2 its area over the surface's. The seed's eqs. 3 and 4 count regions, which is the same
for regions of equal area.
"""
from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from stages.posture import machinable, zmap
from stages.posture.efficiency import psi_deg
from stages.posture.offset import OffsetMesh
from stages.posture.part import Part


def scores(areas, lam, delta, alpha: float) -> tuple[float, float, float, float]:
    """(Φ1, Φ2, E, machinable area mm²) of one orientation.

    Parameters
    ----------
    areas : (n,) mm²; lam : (n,) λ of each region; delta : (n,) bool δ; alpha : weight of Φ2.
    """
    a_m = float(areas[delta].sum())
    phi1 = float((areas[delta] * lam[delta]).sum() / a_m) if a_m > 0 else 0.0
    phi2 = a_m / float(areas.sum())
    return phi1, phi2, (1 - alpha) * phi1 + alpha * phi2, a_m


def evaluate(part: Part, offset: OffsetMesh, grid: dict, efficiency, alpha: float, cell_mm: float,
             backend: str = "auto", tile_px: int = 2048, progress=None) -> dict:
    """Every orientation of ``grid`` (``orientations.grid``) evaluated on ``part``.

    Parameters
    ----------
    efficiency : λ(ψ in degrees) → efficiency (``efficiency.sin2psi`` or a ``Table``).
    progress : optional callable(done, total).

    Returns
    -------
    dict with (n,) ``phi1, phi2, e, area_mm2`` and ``delta``: (n, ceil(n_regions / 8)) uint8, each
    orientation's δ packed in bits (``np.packbits``).
    """
    from stages.posture.orientations import frames as make_frames
    axes = grid["axis"]
    frames = make_frames(axes, grid["up"])
    views, owner = zmap.windows(offset, frames, cell_mm, tile_px)
    images = zmap.zmaps(offset, views, backend)
    n = len(axes)
    out = {k: np.zeros(n) for k in ("phi1", "phi2", "e", "area_mm2")}
    out["delta"] = np.zeros((n, (part.n + 7) // 8), np.uint8)
    nrm = part.normals
    done = 0
    # products of (n, 3) arrays with 3-vectors: threaded BLAS only spins against the renderer's threads
    with threadpool_limits(1):
        for k, delta in machinable.orientation_flags(part, offset, axes, frames, views, owner, images, cell_mm):
            lam = efficiency(psi_deg(nrm, axes[k]))
            out["phi1"][k], out["phi2"][k], out["e"][k], out["area_mm2"][k] = scores(part.areas, lam, delta, alpha)
            out["delta"][k] = np.packbits(delta)
            done += 1
            if progress is not None:
                progress(done, n)
    return out


def unpack(delta_bits, n_regions: int) -> np.ndarray:
    """(m, n_regions) bool from packed rows."""
    return np.unpackbits(np.atleast_2d(delta_bits), axis=1, count=n_regions).astype(bool)
