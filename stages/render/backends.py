"""Choosing a back end for ``render.backend``."""
from __future__ import annotations

import logging

from stages import InputError
from stages.render.base import Renderer

log = logging.getLogger(__name__)


_RENDERERS = {}


def make_renderer(backend: str = "auto") -> Renderer:
    """Renderer for ``render.backend``: ``"gl"``, ``"cpu"`` or ``"auto"``.

    ``auto`` uses gl when a headless EGL context opens and falls back to cpu otherwise, logging
    why. ``gl`` raises RuntimeError when no context opens. Renderers are cached per process.
    """
    if backend not in ("auto", "gl", "cpu"):
        raise InputError(f"render.backend: {backend!r} is not one of auto, gl, cpu")
    if backend in _RENDERERS:
        return _RENDERERS[backend]
    if backend == "cpu":
        from stages.render.cpu import CPURenderer
        r = CPURenderer()
    elif backend == "gl":
        from stages.render.gl import GLRenderer
        r = GLRenderer()
    else:
        try:
            r = make_renderer("gl")
        except Exception as e:
            log.warning("render.backend auto: using the cpu back end (%s)", e)
            r = make_renderer("cpu")
    _RENDERERS[backend] = r
    return r
