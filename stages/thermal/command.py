"""``pipeline thermal-fit``: a drift model from on-machine reference measurements, and its prediction.

Writes ``drift.yaml`` (the model, the workflow's ``drift:`` file), ``drift.json`` (the fit: residual
RMS per axis, standard errors) and ``drift.png`` (measured and fitted drift over time) beside it;
with ``predict`` the model's drift at the times of that file. Files are written under temporary
names and renamed at the end: an error leaves no partial output.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import yaml

from stages import InputError
from stages.thermal.fit import fit_drift
from stages.thermal.io import model_columns, read_table
from stages.thermal.model import AXES, DriftModel


def load_model(path) -> DriftModel:
    """A drift model written by ``thermal-fit``."""
    path = Path(path)
    try:
        d = yaml.safe_load(path.read_text())
        if not isinstance(d, dict):
            raise InputError(f"{path}: not a drift model written by `pipeline thermal-fit` (a mapping of keys "
                             f"kind, time_constants_s, axes, ...; got {type(d).__name__})")
        return DriftModel.from_dict(d)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (KeyError, TypeError, ValueError, yaml.YAMLError) as e:
        raise InputError(f"{path}: not a drift model written by `pipeline thermal-fit` ({e})") from None


def predict_file(model: DriftModel, times, out_csv) -> int:
    """Write the model's drift at the times (and heat input, positions) of ``times``; returns rows."""
    data = read_table(times, required=("time_s", *model.needs()))
    pred = model.predict(data)
    tmp = Path(str(out_csv) + ".tmp")
    cols = np.column_stack([data["time_s"]] + [pred[f"d{a}_um"] for a in AXES])
    np.savetxt(tmp, cols, delimiter=",", fmt=["%.3f", "%.4f", "%.4f", "%.4f"],
               header="time_s,dx_um,dy_um,dz_um", comments="")
    os.replace(tmp, Path(out_csv))
    return len(cols)


def _plot(data: dict, model: DriftModel, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t_h = data["time_s"] / 3600.0
    pred = model.predict(data)
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for ax, a in zip(axes, AXES):
        ax.plot(t_h, data[f"d{a}_um"], ".", ms=3, color="0.4", label="measured")
        ax.plot(t_h, pred[f"d{a}_um"], "-", color="tab:red", lw=1.5, label="fitted")
        ax.set_ylabel(f"d{a} (µm)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best")
    axes[0].set_title("thermal drift: " + ", ".join(f"τ{k + 1} = {t / 60:.1f} min" for k, t in enumerate(model.taus_s)))
    axes[-1].set_xlabel("time (h)")
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)


def thermal_fit_command(measurements, out_yaml, sources: int = 2) -> dict:
    """Fit the drift model to ``measurements`` and write ``out_yaml`` (+ ``.json``, ``.png``).

    Returns
    -------
    dict : the fit report (also ``<out>.json``) with the model.
    """
    data = read_table(measurements)
    cols = model_columns(data)
    n = len(data["time_s"])
    # the time constants and every axis's linear coefficients
    shape = DriftModel(np.ones(sources), positions=cols["positions"], temperatures=cols["temperatures"])
    params = sources + 3 * len(shape.columns())
    if 3 * n < params + 1:
        raise InputError(f"{measurements}: {n} measurement lines give {3 * n} values, fewer than the model's "
                         f"{params} parameters + 1 (for the noise): measure more often or use fewer --sources")
    model, report = fit_drift(data, sources, **cols)
    report["model"] = model.to_dict()
    report["measurements"] = str(measurements)
    out = Path(out_yaml)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmps = [Path(str(out.with_suffix(s)) + ".tmp") for s in (".yaml", ".json", ".png")]
    tmps[0].write_text(yaml.safe_dump(model.to_dict(), sort_keys=False))
    tmps[1].write_text(json.dumps(report, indent=1))
    _plot(data, model, tmps[2])
    os.replace(tmps[0], out)
    os.replace(tmps[1], out.with_suffix(".json"))
    os.replace(tmps[2], out.with_suffix(".png"))
    return report
