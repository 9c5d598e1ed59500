"""Make the posture job's sample parts in ``data_samples/posture/`` (deterministic).

    python scripts/make_posture_sample.py [--part cavity|fan|both] [--out FILE] [--rings 48] [--sectors 320]

``cavity.ply`` (``workflows/posture.yaml``): a mould cavity insert with undercuts, what a shop
machines 3+2. A block 92 × 72 mm on top, 20 mm high, its outer sides drafted 5° out to the base;
in its top a pocket 70 × 50 mm at the rim (corners of 10 mm radius in plan), 15 mm deep, with
4 mm fillets at the floor. The pocket's +X and −X walls are undercuts: they overhang, drafted −15°
and −10° (the pocket widens downwards), flat; its ±Y walls are drafted 3°. Built as closed loops
(floor, fillets and walls, top, sides, base) joined by strips: one closed sheet, watertight.

``fan.ply`` (``workflows/posture_fan.yaml``): a fan-like impeller (the seed's Fig. 3 a is a fan): a
gently domed hub of radius 40 mm (the rim 6 mm above the base), with five blades 7 mm high that
turn by 15° from root to tip and lean 40° sideways, so the flank on the lean side overhangs: an
undercut for a vertical tool. The required surface is the hub and the blades, open at the rim.
Built as a height field over polar rings and sectors, then sheared sideways at the blades: a one
to one map of space, so the surface stays one sheet (manifold, consistently wound, normals out).
``bench/posture_bench.py`` makes the same fan with 100,000 triangles.
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


# --- the cavity insert --------------------------------------------------------------------------------------
TOP, DEPTH, CORNER, FILLET = 20.0, 15.0, 10.0, 4.0    # block height, pocket depth, plan corner and floor fillet radii
RIM = (35.0, 25.0, -35.0, -25.0)                    # the pocket's rim: x of the +X wall, y of +Y, x of −X, y of −Y
OUTER, OUTER_CORNER, OUTER_DRAFT = (46.0, 36.0, -46.0, -36.0), 12.0, 5.0
WALLS = (-15.0, 3.0, -10.0, 3.0)                    # draft of the +X, +Y, −X, −Y walls, degrees (< 0: undercut)
SIDE_PTS, CORNER_PTS = (10, 14), 10                 # points along the X and the Y sides, and round a corner
# rows down a wall, along a fillet; rings over the floor and the base. Rows of 2 mm keep the corners (blends of an
# undercut's and a drafted wall's profiles) smooth: with rows of 5 mm their facets' creases left slivers only
# grazing tilts reach (0.8 mm² at 0.4 mm cells, a fourth posture)
WALL_ROWS, FILLET_ROWS, FLOOR_RINGS = 6, 10, 4


def wall_profile(draft_deg: float) -> np.ndarray:
    """(u, ζ) down a wall, from the rim to the floor: u inward from the rim, ζ down from the top (mm);
    the straight wall (``WALL_ROWS`` rows) then the floor fillet (``FILLET_ROWS``), tangent to both."""
    a = np.radians(draft_deg)
    foot = DEPTH - FILLET + FILLET * np.sin(a)                 # where the fillet meets the wall
    s = np.linspace(0, 1, WALL_ROWS + 1)
    uc = (FILLET + (DEPTH - FILLET) * np.sin(a)) / np.cos(a)   # the fillet's centre, inward from the rim
    b = a + (np.pi / 2 - a) * np.arange(1, FILLET_ROWS + 1) / FILLET_ROWS
    return np.concatenate([np.stack([s * foot * np.tan(a), s * foot], -1),
                           np.stack([uc - FILLET * np.cos(b), DEPTH - FILLET + FILLET * np.sin(b)], -1)])


def corner_centres(sides, radius: float) -> np.ndarray:
    xp, yp, xm, ym = sides
    return np.array([[xp - radius, yp - radius], [xm + radius, yp - radius], [xm + radius, ym + radius],
                     [xp - radius, ym + radius]])


def rounded_loop(sides, u, z, radius: float) -> np.ndarray:
    """A closed loop counter-clockwise from above: the sides +X, +Y, −X, −Y at ``sides`` moved inward
    by ``u`` (4,) at heights ``z`` (4,), and corner arcs about fixed centres whose radius ``radius − u``
    and height blend smoothly from one side's to the next (the same points on every loop)."""
    centres = corner_centres(sides, radius)
    pts = []
    for k in range(4):
        nxt, n = (k + 1) % 4, SIDE_PTS[k % 2]
        c0, c1, t = centres[k - 1], centres[k], np.arange(n) / n
        pos = np.full(n, sides[k] - u[k] * (1 if k < 2 else -1))
        along = c0[1 - k % 2] + (c1[1 - k % 2] - c0[1 - k % 2]) * t
        xy = (pos, along) if k % 2 == 0 else (along, pos)
        pts.append(np.stack([*xy, np.full(n, z[k])], -1))
        t = np.arange(CORNER_PTS) / CORNER_PTS
        w = t * t * (3 - 2 * t)
        phi = np.pi / 2 * (k + t)
        r = radius - ((1 - w) * u[k] + w * u[nxt])
        pts.append(np.stack([c1[0] + r * np.cos(phi), c1[1] + r * np.sin(phi), (1 - w) * z[k] + w * z[nxt]], -1))
    return np.concatenate(pts)


def _towards(loop, k: int, n: int) -> np.ndarray:
    """The loop scaled by k/n towards the middle of its bounding box (it is convex)."""
    mid = 0.5 * (loop.min(0) + loop.max(0))
    return mid + (loop - mid) * k / n


def cavity():
    """(vertices, faces) of the cavity insert: loops from the floor's middle out and up the pocket,
    across the top, down the outer sides and in over the base, joined by strips and closed by fans."""
    prof = np.stack([wall_profile(d) for d in WALLS], 1)                 # (rows, 4 walls, (u, ζ))
    pocket = [rounded_loop(RIM, p[:, 0], TOP - p[:, 1], CORNER) for p in prof][::-1]     # floor → rim
    top = rounded_loop(OUTER, np.zeros(4), np.full(4, TOP), OUTER_CORNER)
    base = rounded_loop(OUTER, np.full(4, -TOP * np.tan(np.radians(OUTER_DRAFT))), np.zeros(4), OUTER_CORNER)
    loops = ([_towards(pocket[0], k, FLOOR_RINGS) for k in range(1, FLOOR_RINGS)] + pocket
             + [0.5 * (pocket[-1] + top), top, base]
             + [_towards(base, k, FLOOR_RINGS) for k in range(FLOOR_RINGS - 1, 0, -1)])
    ends = [_towards(pocket[0], 0, 1)[0], _towards(base, 0, 1)[0]]
    n = len(loops[0])
    V = np.concatenate([ends[:1], *loops, ends[1:]])
    idx = 1 + np.arange(len(loops) * n).reshape(len(loops), n)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], idx[1:], nxt[1:], nxt[:-1]
    quads = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    first = np.stack([np.zeros(n, np.int64), idx[0], nxt[0]], 1)
    last = np.stack([np.full(n, len(V) - 1), nxt[-1], idx[-1]], 1)
    return V, np.concatenate([first, quads, last])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("cavity", "fan", "both"), default="both")
    ap.add_argument("--out", help="the file (with one --part); default data_samples/posture/<part>.ply")
    ap.add_argument("--rings", type=int, default=48, help="the fan's polar rings")
    ap.add_argument("--sectors", type=int, default=320, help="the fan's sectors")
    args = ap.parse_args()
    import trimesh
    parts = ("cavity", "fan") if args.part == "both" else (args.part,)
    if args.out and len(parts) > 1:
        ap.error("--out needs one --part")
    for name in parts:
        V, F = cavity() if name == "cavity" else fan(args.rings, args.sectors)
        mesh = trimesh.Trimesh(V, F, process=False)
        out = Path(args.out or Path(__file__).resolve().parent.parent / f"data_samples/posture/{name}.ply")
        out.parent.mkdir(parents=True, exist_ok=True)
        mesh.export(out, encoding="binary")
        print(f"{out}: {len(F)} triangles, {mesh.area:.0f} mm², winding consistent {mesh.is_winding_consistent}, "
              f"watertight {mesh.is_watertight}" + (f", {mesh.volume:.0f} mm³" if mesh.is_watertight else ""))


if __name__ == "__main__":
    main()
