"""Make the posture job's sample part ``data_samples/posture/fan.ply`` (deterministic).

    python scripts/make_posture_sample.py [--out data_samples/posture/fan.ply] [--rings 48] [--sectors 320]

A fan-like impeller (the seed's Fig. 3 a is a fan): a gently domed hub of radius 40 mm (the
rim 6 mm above the base), with five blades 7 mm high that turn by 15° from root to tip
and lean 40° sideways, so the flank on the lean side overhangs: an undercut for a vertical tool.
The required surface is the hub and the blades, open at the rim.
Built as a height field over polar rings and sectors, then sheared sideways at the blades: a one
to one map of space, so the surface stays one sheet (manifold, consistently wound, normals out).
``bench/posture_bench.py`` makes the same part with 100,000 triangles.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

R, HUB, DOME = 40.0, 6.0, 4.0              # rim radius, side height, hub dome rise (mm)
BLADES, TWIST, LEAN = 5, np.radians(15.0), np.radians(40.0)
RHO_IN, RHO_OUT, BLADE_H, HALF_W = 10.0, 36.0, 7.0, 7.0   # blade span, height and half width (mm)


def hub(rho):
    return HUB + DOME * (1 - (rho / R) ** 2)


def blade_height(rho, phi):
    """Height of the blades above the hub at polar (rho, phi)."""
    span = np.clip((rho - RHO_IN) / (RHO_OUT - RHO_IN), 0, 1)
    amp = BLADE_H * np.sin(np.pi * span) ** 0.7
    out = np.zeros(np.broadcast(rho, phi).shape)
    for k in range(BLADES):
        centre = 2 * np.pi * k / BLADES + TWIST * span
        dphi = (phi - centre + np.pi) % (2 * np.pi) - np.pi
        s = dphi * np.maximum(rho, 1e-9) / HALF_W
        out = np.maximum(out, amp * np.clip(1 - s * s, 0, None) ** 2)
    return out


def fan(rings: int = 48, sectors: int = 320, wall: int = 0):
    """(vertices, faces) of the fan: ``rings`` polar rings, ``sectors`` around, ``wall`` rows on the side."""
    phi = 2 * np.pi * np.arange(sectors) / sectors
    rho = R * np.arange(1, rings + 1) / rings
    P, Q = np.meshgrid(rho, phi, indexing="ij")                       # (rings, sectors)
    b = blade_height(P, Q)
    Z = hub(P) + b
    ang = Q + np.tan(LEAN) * b / P                                    # the blades lean sideways
    top = np.stack([P * np.cos(ang), P * np.sin(ang), Z], -1).reshape(-1, 3)
    zs = hub(R) * (1 - np.arange(1, wall + 1) / wall)                 # the side, down to z = 0
    side = np.stack([np.broadcast_to(R * np.cos(phi), (wall, sectors)), np.broadcast_to(R * np.sin(phi), (wall, sectors)),
                     np.broadcast_to(zs[:, None], (wall, sectors))], -1).reshape(-1, 3)
    V = np.concatenate([[[0.0, 0.0, hub(0.0)]], top, side])
    idx = 1 + np.arange((rings + wall) * sectors).reshape(rings + wall, sectors)
    nxt = np.roll(idx, -1, axis=1)
    centre = np.stack([np.zeros(sectors, np.int64), idx[0], nxt[0]], 1)
    a, b2, c, d = idx[:-1], idx[1:], nxt[1:], nxt[:-1]
    quads = np.concatenate([np.stack([a, b2, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return V, np.concatenate([centre, quads])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "data_samples/posture/fan.ply"))
    ap.add_argument("--rings", type=int, default=48)
    ap.add_argument("--sectors", type=int, default=320)
    args = ap.parse_args()
    import trimesh
    V, F = fan(args.rings, args.sectors)
    mesh = trimesh.Trimesh(V, F, process=False)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    mesh.export(args.out, encoding="binary")
    print(f"{args.out}: {len(F)} triangles, {mesh.area:.0f} mm², winding consistent {mesh.is_winding_consistent}")


if __name__ == "__main__":
    main()
