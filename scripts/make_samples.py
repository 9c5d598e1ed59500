"""Make the bundled sample data under ``data_samples/`` (deterministic).

Run from the project root::

    python scripts/make_samples.py [--source PATH_TO/ktoolcav.stl] [--out data_samples]
                                   [--only all|process|rest_overload]

Uses ``opencamlib`` (one of the project's dependencies) for the drop-cutter and waterline
toolpaths; all of it takes about 13 minutes on two cores (``--only process`` 10, ``--only
rest_overload`` half a minute). The README it writes says what each file is, how it is made and
what the finishing tools meet; ``scripts/measure_samples.py`` measures that again on the files.

What it writes (all lengths mm, machine frame: tool axis +Z; the part's min corner at X0 Y0, its
parting face at Z0, the part below it down to Z-41.275; NC coordinates are the tool tip, as
OpenCAMLib's cutter location is: checked on a flat and a tilted facet before anything is written):

``models/mould.stl``
    Nominal (design) model: the cavity insert ``ktoolcav.stl`` of the OpenCAMLib repository
    (folder ``stl/``, LGPL-2.1), in inches, scaled ×25.4 and rotated so that its cavity face
    looks up (+Z): machine (X, Y, Z) = 25.4 · (x + 2, z + 1.5, −y) of the source.
``models/semi.stl``, ``nc/10_steep_t1.nc``, ``nc/20_shallow_t1.nc``, ``nc/30_pencil_t2.nc``
    The finishing process (:mod:`samples_process`, :mod:`samples_programs`): the semi-finished
    stock, the lower envelope of the swept balls of a steep-and-shallow semi-finishing with rest
    passes that leaves 0.2 mm (:mod:`samples_stock`), and the finishing programs machined in
    that order on it: Z-level contours and a raster with a Ø10 ball T1, then rest passes with a
    Ø4 ball T2 where a Ø10 cannot reach.
``rest_overload/semi.stl``, ``rest_overload/nc/mould_finish_t1.nc``, ``rest_overload/nc/mould_contour_t1.nc``
    The heavy-rest case (:mod:`samples_rest_overload`), byte for byte as first made.
``tools/t1_profile.csv``
    Measured contour error of the ball cutter T1 per contact angle: ``contact_deg, error_um``,
    0–90° in 0.1° steps; positive = tool smaller than nominal there. A synthetic but
    realistic measurement: slight undersize growing toward the equator, a bump near 55°,
    0.05 µm noise (seed 2), low-pass filtered as seed 002 prescribes.
``machine/frf_xy.csv``
    Tool-tip compliance FRF ``freq_hz, xx_re, xx_im, yy_re, yy_im`` in µm/N, 0–5000 Hz in 2 Hz
    steps: two modes per axis (x: 850 Hz ζ0.03 k2.0 N/µm and 2300 Hz ζ0.05 k6.0 N/µm;
    y: 910 Hz ζ0.035 k2.3 N/µm and 2450 Hz ζ0.045 k6.5 N/µm), receptance
    G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn, plus measurement noise (seed 1).
``README.md``
    The users' manual of the above (:mod:`samples_readme`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

# scripts/ is on sys.path when run as a script
import samples_rest_overload as rest  # noqa: E402
from samples_build import make_process  # noqa: E402
from samples_cam import DEFAULT_SOURCE, check_cl_is_tip, load_nominal, ocl_surface, roundtrip_stl  # noqa: E402
from samples_geom import Grid  # noqa: E402
from samples_programs import PROGRAMS  # noqa: E402
from samples_readme import render as render_readme  # noqa: E402


# ------------------------------------------------------------------------- tool and machine data
def tool_profile() -> np.ndarray:
    """Measured contour error of the ball cutter per contact angle (µm, + = undersize)."""
    q = np.round(np.arange(0, 900 + 1) * 0.1, 1)
    s = q / 90.0
    err = 0.6 + 2.4 * s ** 2 + 0.9 * np.exp(-0.5 * ((q - 55.0) / 6.0) ** 2)
    rng = np.random.default_rng(2)
    noisy = err + rng.normal(0.0, 0.05, q.size)
    # low-pass (seed 002): Gaussian kernel, sigma 1 deg, edges mirrored
    k = np.exp(-0.5 * (np.arange(-30, 31) * 0.1 / 1.0) ** 2)
    k /= k.sum()
    padded = np.concatenate([noisy[30:0:-1], noisy, noisy[-2:-32:-1]])
    return np.column_stack([q, np.convolve(padded, k, mode="valid")])


FRF_MODES = {
    "xx": [(850.0, 0.03, 2.0), (2300.0, 0.05, 6.0)],
    "yy": [(910.0, 0.035, 2.3), (2450.0, 0.045, 6.5)],
}


def frf_table() -> np.ndarray:
    """Compliance FRF of the tool tip, µm/N, from modal parameters plus noise."""
    f = np.arange(0, 5000 + 1, 2, dtype=np.float64)
    rng = np.random.default_rng(1)
    cols = [f]
    for axis in ("xx", "yy"):
        G = np.zeros(f.size, complex)
        for fn, zeta, k in FRF_MODES[axis]:
            r = f / fn
            G += 1.0 / (k * (1.0 - r ** 2 + 2j * zeta * r))
        noise = (rng.normal(0, 1, f.size) + 1j * rng.normal(0, 1, f.size))
        G = G + noise * (0.002 + 0.005 * np.abs(G))
        cols += [G.real, G.imag]
    return np.column_stack(cols)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", default=DEFAULT_SOURCE, help="path of ktoolcav.stl (inches)")
    ap.add_argument("--out", default="data_samples", help="output folder")
    ap.add_argument("--only", choices=("all", "process", "rest_overload"), default="all",
                    help="process: the process's stock and programs; rest_overload: the heavy-rest case "
                         "(each with the nominal; the README needs all)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    t0 = time.time()

    def log(*a):
        print(f"[{time.time() - t0:6.0f} s]", *a, flush=True)

    check_cl_is_tip()
    nominal = roundtrip_stl(load_nominal(args.source), out / "models" / "mould.stl")
    tris = np.asarray(nominal.triangles, dtype=np.float64)
    surf = ocl_surface(tris)
    log(f"nominal: {len(nominal.faces)} faces, bounds {np.round(nominal.bounds, 2).tolist()}")
    ours = ["models/mould.stl"]
    if args.only in ("all", "process"):
        proc = make_process(out, surf, tris, Grid(tris, 2.0), float(nominal.bounds[0, 2]), log=log)
        ours += ["models/semi.stl"] + [f"nc/{n}" for n in PROGRAMS]
    if args.only in ("all", "rest_overload"):
        ro = rest.make(out / "rest_overload", surf, tris, z_bottom=float(nominal.bounds[0, 2]))
        log("rest_overload:", ro)
        ours += ["rest_overload/semi.stl", "rest_overload/nc/mould_finish_t1.nc", "rest_overload/nc/mould_contour_t1.nc"]
    if args.only == "all":
        (out / "tools").mkdir(parents=True, exist_ok=True)
        np.savetxt(out / "tools" / "t1_profile.csv", tool_profile(), fmt=["%.1f", "%.4f"],
                   delimiter=",", header="contact_deg,error_um", comments="")
        (out / "machine").mkdir(parents=True, exist_ok=True)
        np.savetxt(out / "machine" / "frf_xy.csv", frf_table(), fmt=["%.0f"] + ["%.6e"] * 4,
                   delimiter=",", header="freq_hz,xx_re,xx_im,yy_re,yy_im", comments="")
        (out / "README.md").write_text(render_readme(nominal, proc, ro, minutes=(time.time() - t0) / 60))
        ours += ["tools/t1_profile.csv", "machine/frf_xy.csv", "README.md"]
    sizes = {k: (out / k).stat().st_size for k in ours}
    for k, v in sizes.items():
        print(f"  {k:40s} {v / 1e6:8.3f} MB")
    print(f"total {sum(sizes.values()) / 1e6:.2f} MB in {time.time() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
