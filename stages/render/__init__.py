"""Depth-test rendering of tools, sweeps and workpieces: one interface, two back ends (DESIGN §2).

``make_renderer("gl" | "cpu" | "auto")`` returns a :class:`Renderer`; windows are :class:`View`,
triangle lists :class:`Scene`. See :mod:`stages.render.base`.
"""
from stages.render.backends import make_renderer
from stages.render.base import (
    Image,
    Renderer,
    CutLog,
    ScanResult,
    Scene,
    View,
    make_scene,
)

__all__ = ["CutLog", "Image", "Renderer", "Scene", "ScanResult", "View", "make_renderer", "make_scene"]
