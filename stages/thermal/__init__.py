"""Thermal drift of the machine (seed 003): the model (:mod:`.model`), its fit to on-machine
reference measurements (:mod:`.fit`), the measurement files (:mod:`.io`) and the
``pipeline thermal-fit`` command (:mod:`.command`)."""
from stages.thermal.command import load_model, predict_file, thermal_fit_command
from stages.thermal.fit import fit_drift
from stages.thermal.model import DriftModel, responses

__all__ = ["DriftModel", "fit_drift", "load_model", "predict_file", "responses", "thermal_fit_command"]
