"""NC programs for tests and benchmarks, written the way CAM post-processors write them."""
from __future__ import annotations

import numpy as np


def raster_program(n_blocks: int, seed: int = 0, per_row: int = 400) -> bytes:
    """A zig-zag raster: rows of short G1 moves over z = f(x, y), rows joined by G2/G3 half circles."""
    rng = np.random.default_rng(seed)
    rows = max(1, n_blocks // (per_row + 1))
    step = 0.5
    lines = ["%", "O1234 (BENCH RASTER)", "(TOOL: BALL D6)", "G90 G17 G21 G40 G49 G80", "T1 M6", "S12000 M3",
             "G0 X0. Y0.", "G0 Z5.", "G1 Z0.5 F1000"]
    n = 10
    for r in range(rows):
        y = r * step
        xs = np.arange(per_row) * 0.25 if r % 2 == 0 else (per_row - 1 - np.arange(per_row)) * 0.25
        zs = 0.5 * np.sin(xs / 7.0) * np.cos(y / 5.0) + rng.normal(0, 1e-4, per_row)
        first = True
        for x, z in zip(xs, zs):
            lines.append(f"N{n} G1 X{x:.3f} Y{y:.3f} Z{z:.3f} F3000" if first else f"N{n} X{x:.3f} Z{z:.3f}")
            first = False
            n += 1
        arc = "G3" if r % 2 == 0 else "G2"
        lines.append(f"N{n} {arc} X{xs[-1]:.3f} Y{y + step:.3f} I0. J{step / 2:.3f}")
        n += 1
    lines += ["G0 Z50.", "M5", "M30", "%"]
    return ("\n".join(lines) + "\n").encode()


def wall_program(offset_um: float = 0.0):
    """Passes of a wall job: a ball Ø10 along +x at y = 0, the wall on its −y side at y = −5 (n = +y,
    q = 90°): a long pass A (x 0–10), a 0.05 mm pass B, a long pass C (x 10.05–20, moved away from
    the wall by ``offset_um``). F1000 S10000: 0.1 mm of feed per revolution, B shorter than it."""
    from stages.nc.moves import split_blocks
    from stages.nc.reader import parse_program
    off = offset_um * 1e-3
    src = (f"%\nO1\nT1 M6\nS10000 M3\nG0 X0 Y0 Z5\nG1 Z0 F1000\nX10\nX10.05\nX10.05 Y{off:.4f}\n"
           f"X20 Y{off:.4f}\nG0 Z5\nM30\n%\n").encode()
    blocks, _ = parse_program(src, "wall.nc", "w")
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 50.0, "merge_max_mm": 0.0},
             "machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 10.0}}
    return split_blocks(blocks, split)
