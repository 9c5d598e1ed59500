"""Pictures of the machined bar: cross-sections and a 3-D view (matplotlib, Agg)."""
from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def sections_png(rows, theta, z_mm, workpiece_radius_mm: float, path, title: str = "") -> None:
    """The sections ``rows`` (k, ntheta) at ``z_mm`` (k,), each over the bar's original circle."""
    plt = _plt()
    k = len(rows)
    cols = min(k, 4)
    nrow = int(np.ceil(k / cols))
    fig, axes = plt.subplots(nrow, cols, figsize=(3.0 * cols, 3.0 * nrow + 0.4), squeeze=False)
    t = np.append(theta, theta[0])
    rw = workpiece_radius_mm
    for ax, r, z in zip(axes.ravel(), rows, z_mm):
        rr = np.append(r, r[0])
        ax.plot(rw * np.cos(t), rw * np.sin(t), "--", color="0.6", lw=0.8)
        ax.fill(rr * np.cos(t), rr * np.sin(t), color="tab:blue", alpha=0.35)
        ax.plot(rr * np.cos(t), rr * np.sin(t), color="tab:blue", lw=1.0)
        ax.set_aspect("equal")
        ax.set_xlim(-1.05 * rw, 1.05 * rw)
        ax.set_ylim(-1.05 * rw, 1.05 * rw)
        ax.set_title(f"z = {z:.2f} mm", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[k:]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    _save(plt, fig, path)


def view3d_png(r, theta, z_mm, path, title: str = "", rings: int = 60) -> None:
    """A 3-D view of the bar as a stack of ``rings`` section outlines coloured along z (matplotlib draws
    a shaded closed surface with its back faces over the front; the STL is the solid for a real view)."""
    plt = _plt()
    r = np.asarray(r)
    idx = np.unique(np.linspace(0, r.shape[0] - 1, min(rings, r.shape[0])).astype(int))
    t = np.append(theta, theta[0])
    rr = np.concatenate([r[idx], r[idx, :1]], axis=1)
    fig = plt.figure(figsize=(9, 5))
    ax = fig.add_subplot(projection="3d", proj_type="ortho")
    for n, (row, z) in enumerate(zip(rr, np.asarray(z_mm)[idx])):
        ax.plot(np.full(t.size, z), row * np.cos(t), row * np.sin(t), color=plt.cm.viridis(n / max(1, len(idx) - 1)), lw=0.9)
    lim = float(rr.max())
    ax.set_ylim(-lim, lim)
    ax.set_zlim(-lim, lim)
    # a long bar is drawn at most four diameters long
    ax.set_box_aspect((min(float(np.ptp(z_mm)), 8 * lim) or 1.0, 2 * lim, 2 * lim))
    ax.view_init(elev=25, azim=-65)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("x (mm)")
    ax.set_zlabel("y (mm)")
    if title:
        ax.set_title(title, fontsize=10)
    _save(plt, fig, path)


def _save(plt, fig, path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)
