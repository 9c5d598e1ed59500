"""Render core: orthographic depth-tested rendering of many small windows at once.

One small interface, two back ends (``stages.render.gl``: moderngl on headless EGL, Mesa's llvmpipe
without a GPU; ``stages.render.cpu``: a numpy z-buffer, the reference in tests and the "software
method" of the speed comparisons). Both take a list of :class:`View` windows and one triangle list
whose triangles name the window they belong to. The shared front end (:func:`_to_atlas`) packs the
windows into an atlas framebuffer (one draw renders all of them), transforms every triangle into
atlas pixels, applies per-triangle depth bias and drops triangles outside their window. The back
ends only rasterise: depth test LESS, per-corner attributes interpolated linearly, fragments outside
the triangle's own window rectangle discarded. Memory is bounded by the atlas and the triangle
budget per draw, never by the size of the program.

A view looks along ``view_dir`` (from below: ``+Z``, the material side; seed para 0045). Depth is
the coordinate along ``view_dir`` from the view centre; nearer = smaller.

:meth:`Renderer.scan` draws a tile's triangles strictly in order (the stock, then the sweeps pass
after pass) and reports per id the fragments that passed the depth test: what each pass cut (claim
7), the final surface with the pass that left each pixel (claim 8), and snapshots of the depth
buffer mid-scan (the material before a prediction point, claim 5).

Per pixel the result holds the winning triangle's ``id`` (first attribute, an integer stored as
float: exact up to 2**24) and two interpolated attributes ``a``, ``b`` (e.g. rotation angle φ and
contact angle q, claim 4), and the depth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ATLAS_PX = 2048                 # default atlas side (grown up to the GL limit for large windows)


TRI_BUDGET = 1_500_000          # triangles per draw (bounds the vertex buffer to ~200 MB)


TIE_DEPTH = 1e-9                # depth (0..1 of the view's range) below which the scan sees a tie
N_ATTR = 4                      # per-corner attributes: id, a, b, c


@dataclass(frozen=True)
class View:
    """Orthographic window.

    center : (3,) point on the view axis (mm). view_dir : (3,) direction the rays travel.
    up : (3,) direction of increasing image rows (projected orthogonal to view_dir).
    width_mm, height_mm : window extent; px_per_mm : resolution.
    near_mm, far_mm : depth range along view_dir relative to ``center``.
    """

    center: tuple
    view_dir: tuple
    up: tuple
    width_mm: float
    height_mm: float
    px_per_mm: float
    near_mm: float
    far_mm: float

    @property
    def shape(self):
        """(rows, cols) in pixels."""
        return (max(1, int(math.ceil(self.height_mm * self.px_per_mm - 1e-9))),
                max(1, int(math.ceil(self.width_mm * self.px_per_mm - 1e-9))))

    def basis(self):
        """Unit vectors (right, up, view_dir) of the image frame."""
        d = np.asarray(self.view_dir, float)
        d = d / np.linalg.norm(d)
        up = np.asarray(self.up, float)
        up = up - (up @ d) * d
        if np.linalg.norm(up) < 1e-9:                      # up parallel to view: any normal
            up = np.cross(d, [1.0, 0, 0]) if abs(d[0]) < 0.9 else np.cross(d, [0, 1.0, 0])
        up /= np.linalg.norm(up)
        right = np.cross(up, d)
        return right, up, d

    def pixel_points(self, rows, cols, depth):
        """3-D points of pixel centres (rows, cols) at ``depth`` along the view direction."""
        right, up, d = self.basis()
        h, w = self.shape
        x = (np.asarray(cols) + 0.5 - w / 2) / self.px_per_mm
        y = (np.asarray(rows) + 0.5 - h / 2) / self.px_per_mm
        c = np.asarray(self.center, float)
        return (c + x[..., None] * right + y[..., None] * up
                + np.asarray(depth, float)[..., None] * d)

    def project(self, points):
        """(cols, rows) pixel coordinates (continuous) and depth of 3-D points."""
        right, up, d = self.basis()
        h, w = self.shape
        p = np.asarray(points, float) - np.asarray(self.center, float)
        return (p @ right * self.px_per_mm + w / 2, p @ up * self.px_per_mm + h / 2, p @ d)


@dataclass
class Image:
    """One rendered window. ``depth`` is +inf and ``id`` -1 where nothing was drawn."""

    view: View
    depth: np.ndarray   # (h, w) float64, mm along view_dir from the view centre
    id: np.ndarray      # (h, w) int64
    a: np.ndarray       # (h, w) float32
    b: np.ndarray       # (h, w) float32
    c: np.ndarray | None = None   # (h, w) float32, the fourth attribute (scans only)


@dataclass
class Scene:
    """Triangles for a batch of windows.

    tris : (n, 3, 3) world corners (mm). attrs : (n, 3, 4) per-corner (id, a, b, c).
    bias : (n,) depth bias in mm added before the depth test (pushes a triangle back).
    window : (n,) index of the view each triangle belongs to.
    """

    tris: np.ndarray
    attrs: np.ndarray
    bias: np.ndarray
    window: np.ndarray

    @staticmethod
    def concat(parts):
        parts = [p for p in parts if p is not None and len(p.tris)]
        if not parts:
            return Scene(np.zeros((0, 3, 3)), np.zeros((0, 3, N_ATTR), np.float32), np.zeros(0),
                         np.zeros(0, np.int64))
        return Scene(np.concatenate([p.tris for p in parts]),
                     np.concatenate([p.attrs for p in parts]),
                     np.concatenate([p.bias for p in parts]),
                     np.concatenate([p.window for p in parts]))


def make_scene(tris, window, tri_id, a=None, b=None, bias=0.0, c=None):
    """Scene from triangles with one id per triangle and per-corner attributes a, b, c."""
    tris = np.asarray(tris, float).reshape(-1, 3, 3)
    n = len(tris)
    attrs = np.zeros((n, 3, N_ATTR), np.float32)
    attrs[:, :, 0] = np.broadcast_to(np.asarray(tri_id, float).reshape(-1, 1) if np.ndim(tri_id)
                                     else tri_id, (n, 3))
    if a is not None:
        attrs[:, :, 1] = np.broadcast_to(a, (n, 3))
    if b is not None:
        attrs[:, :, 2] = np.broadcast_to(b, (n, 3))
    if c is not None:
        attrs[:, :, 3] = np.broadcast_to(c, (n, 3))
    return Scene(tris, attrs, np.broadcast_to(np.asarray(bias, float), (n,)).copy(),
                 np.broadcast_to(np.asarray(window), (n,)).astype(np.int64))


def _pack(views, atlas_px):
    """Shelf-pack windows into atlases; returns per view (atlas index, x0, y0)."""
    out, atlas, x, y, row_h = [], 0, 0, 0, 0
    for v in views:
        h, w = v.shape
        if w > atlas_px or h > atlas_px:
            raise ValueError(f"window {w}x{h} px larger than the atlas {atlas_px}")
        if x + w > atlas_px:
            x, y, row_h = 0, y + row_h, 0
        if y + h > atlas_px:
            atlas, x, y, row_h = atlas + 1, 0, 0, 0
        out.append((atlas, x, y))
        x += w
        row_h = max(row_h, h)
    return out


def _to_atlas(views, scene, offsets):
    """Atlas-space vertices: (n, 3, 3) [x_px, y_px, depth01], attrs+depth (n, 3, 5), rect (n, 4).

    ``scene.window`` must be sorted (the renderer sorts it): each window's triangles are then a
    contiguous block transformed by one small matrix product.
    """
    n = len(scene.tris)
    xyz = np.empty((n, 3, 3), np.float64)
    rect = np.empty((n, 4), np.float32)
    bounds = np.empty((n, 2), np.float64)        # width, height of the triangle's window (px)
    span = np.empty(n, np.float64)
    starts = np.searchsorted(scene.window, np.arange(len(views) + 1))
    for w, v in enumerate(views):
        a, b = starts[w], starts[w + 1]
        if a == b:
            continue
        h, wd = v.shape
        M = np.stack(v.basis())                                   # rows: right, up, d
        loc = (scene.tris[a:b] - np.asarray(v.center, float)) @ M.T
        ox, oy = offsets[w][1], offsets[w][2]
        xyz[a:b, :, 0] = loc[..., 0] * v.px_per_mm + wd / 2
        xyz[a:b, :, 1] = loc[..., 1] * v.px_per_mm + h / 2
        xyz[a:b, :, 2] = loc[..., 2] + scene.bias[a:b, None] - v.near_mm
        rect[a:b] = (ox, oy, ox + wd, oy + h)
        bounds[a:b] = (wd, h)
        span[a:b] = v.far_mm - v.near_mm
    lo = np.minimum(np.minimum(xyz[:, 0], xyz[:, 1]), xyz[:, 2])   # faster than min(axis=1)
    hi = np.maximum(np.maximum(xyz[:, 0], xyz[:, 1]), xyz[:, 2])
    # drop triangles entirely outside their window or depth range
    keep = ((hi[:, 0] >= 0) & (lo[:, 0] <= bounds[:, 0]) & (hi[:, 1] >= 0) & (lo[:, 1] <= bounds[:, 1])
            & (hi[:, 2] >= 0) & (lo[:, 2] <= span))
    xyz, rect, span = xyz[keep], rect[keep], span[keep]
    pos = np.empty(xyz.shape, np.float64)
    pos[..., 0] = xyz[..., 0] + rect[:, None, 0]
    pos[..., 1] = xyz[..., 1] + rect[:, None, 1]
    pos[..., 2] = xyz[..., 2] / span[:, None]
    attrs = np.empty((len(pos), 3, N_ATTR + 1), np.float32)
    attrs[..., :N_ATTR] = scene.attrs[keep]
    attrs[..., N_ATTR] = xyz[..., 2]
    return pos, attrs, rect.astype(np.float64), scene.window[keep]


@dataclass
class CutLog:
    """Every fragment that passed the depth test of a scan: the depth each cut left.

    pix : (m,) int64 flat pixel index (row · width + column); ident : (m,) int32 id of the triangle;
    depth : (m,) float32 depth (mm along the view from its centre). Entries are in no particular
    order; within one id at one pixel the nearest is what the cut left.
    """

    pix: np.ndarray
    ident: np.ndarray
    depth: np.ndarray

    @staticmethod
    def concat(parts):
        parts = list(parts)
        if not parts:
            return CutLog(np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.float32))
        return CutLog(np.concatenate([p.pix for p in parts]), np.concatenate([p.ident for p in parts]),
                      np.concatenate([p.depth for p in parts]))


@dataclass
class ScanResult:
    """Result of :meth:`Renderer.scan`.

    counts : (n_ids, n_bins) fragments of each id that passed the depth test, by bin of ``a``.
    b_max : (n_ids,) largest ``b`` among them (-inf where none passed).
    final : the final image: per pixel the last passing fragment's id (-1: none), ``b``, ``c``
        and depth (+inf off the stock); ``a`` is not kept (NaN).
    stock_depth : (h, w) depth of the stock's top (mm along the view; +inf off the stock).
    log : the :class:`CutLog` when asked for, else None.
    """

    counts: np.ndarray
    b_max: np.ndarray
    final: Image
    stock_depth: np.ndarray
    log: "CutLog | None" = None


class Renderer:
    """Render a batch of windows. Subclasses implement :meth:`_raster` only."""

    name = "base"
    atlas_px = ATLAS_PX
    tri_budget = TRI_BUDGET

    def render(self, views, scene: Scene):
        """Render ``scene`` into ``views``; returns one :class:`Image` per view."""
        views = list(views)
        if not views:
            return []
        atlas_px = self.atlas_px
        big = max(max(v.shape) for v in views)
        if big > atlas_px:
            atlas_px = min(self.max_atlas_px(), 1 << int(math.ceil(math.log2(big))))
        presorted = bool(np.all(scene.window[1:] >= scene.window[:-1]))
        order = None if presorted else np.argsort(scene.window, kind="stable")
        starts = np.searchsorted(scene.window if presorted else scene.window[order],
                                 np.arange(len(views) + 1))
        counts = np.diff(starts)
        # group windows into draws bounded by atlas area and triangle budget
        offsets = _pack(views, atlas_px)
        images = [None] * len(views)
        i = 0
        while i < len(views):
            atlas = offsets[i][0]
            j, ntri = i, 0
            while j < len(views) and offsets[j][0] == atlas and (j == i or ntri + counts[j] <= self.tri_budget):
                ntri += counts[j]
                j += 1
            sub = views[i:j]
            sub_off = _pack(sub, atlas_px)           # repack from origin for this draw
            sel = slice(starts[i], starts[j]) if presorted else order[starts[i]:starts[j]]
            sc = Scene(scene.tris[sel], scene.attrs[sel], scene.bias[sel], scene.window[sel] - i)
            pos, attrs, rect, _ = _to_atlas(sub, sc, sub_off)
            W = max(o[1] + v.shape[1] for o, v in zip(sub_off, sub))
            H = max(o[2] + v.shape[0] for o, v in zip(sub_off, sub))
            color = self._raster(pos, attrs, rect, (H, W))
            for v, o, n in zip(sub, sub_off, range(i, j)):
                h, w = v.shape
                blk = color[o[2]:o[2] + h, o[1]:o[1] + w]
                empty = blk[..., 0] < -0.5
                depth = np.where(empty, np.inf, blk[..., 3].astype(np.float64) + v.near_mm)
                images[n] = Image(v, depth, np.where(empty, -1, np.rint(blk[..., 0])).astype(np.int64),
                                  blk[..., 1].copy(), blk[..., 2].copy())
            i = j
        return images

    def scan(self, view, stock: Scene, batches, n_ids: int, n_bins: int = 20, log: bool = False,
             before=()) -> ScanResult:
        """Ordered depth scan of one window: claims 7 and 8 in one render, and the cut log.

        The stock is drawn first (its top surface: the farthest stock face, so pixels off the
        stock can never be cut), then the scenes of ``before`` (what earlier programs removed:
        neither counted nor logged, and part of ``stock_depth``), then the triangles of
        ``batches`` strictly in their order with
        the depth test LESS and depth writes, as the machine removes material pass after pass.
        A fragment passes where it is nearer than the stock and everything drawn before it: for
        a sweep that is where the pass cuts. Per id (attribute 0, ``>= 0``; negative ids are
        drawn but not counted) the scan counts passing fragments in ``n_bins`` bins of attribute
        ``a`` (in [0, 1], e.g. the position along the pass) and keeps the largest attribute ``b``
        (e.g. the contact angle). The final image holds, per pixel, the last passing fragment:
        the final surface and which id left it. With ``log`` every passing fragment's pixel, id
        and depth are kept (:class:`CutLog`): the depth a cut replaced is the one before it there.

        Memory is bounded by the window, the triangle budget per draw and the log: ``batches`` is
        any iterable of scenes (e.g. a generator over pass ranges), each split into draws.
        """
        h, w = view.shape
        if max(h, w) > self.max_atlas_px():
            raise ValueError(f"scan window {w}x{h} px larger than {self.max_atlas_px()}")
        offs = [(0, 0, 0)]
        counts = np.zeros((n_ids, n_bins), np.int64)
        b_max = np.full(n_ids, -np.inf)
        logs = []
        self._scan_start((h, w), n_ids, n_bins, log)
        try:
            pos, attrs, rect, _ = _to_atlas([view], stock, offs)
            self._scan_stock(pos, attrs, rect)
            for sc in before:
                for pos, attrs, rect in self._scan_parts(view, sc):
                    self._scan_draw(pos, attrs, rect, counts, b_max, n_bins, log=False)
            stock01 = self._scan_depth(0, 0, h, w)
            for sc in batches:
                for pos, attrs, rect in self._scan_parts(view, sc):
                    self._scan_draw(pos, attrs, rect, counts, b_max, n_bins, log=log)
                if log:
                    logs.append(self._scan_log())
        finally:
            color = self._scan_finish(counts, b_max)
        empty = color[..., 0] < -0.5
        depth = np.where(empty, np.inf, color[..., 3].astype(np.float64) + view.near_mm)
        final = Image(view, depth, np.where(empty, -1, np.rint(color[..., 0])).astype(np.int64),
                      np.full((h, w), np.nan, np.float32), color[..., 1].copy(), color[..., 2].copy())
        stock_depth = np.where(stock01 > 0, stock01 * (view.far_mm - view.near_mm) + view.near_mm, np.inf)
        cut = None
        if log:
            cut = CutLog.concat(logs)
            cut.depth = (cut.depth.astype(np.float64) + view.near_mm).astype(np.float32)
        return ScanResult(counts, b_max, final, stock_depth, cut)

    def _scan_parts(self, view, sc: Scene):
        """A scan's scene in draws of at most the triangle budget, in its order."""
        for a in range(0, len(sc.tris), self.tri_budget):
            part = Scene(sc.tris[a:a + self.tri_budget], sc.attrs[a:a + self.tri_budget], sc.bias[a:a + self.tri_budget],
                         np.zeros(min(self.tri_budget, len(sc.tris) - a), np.int64))
            pos, attrs, rect, _ = _to_atlas([view], part, [(0, 0, 0)])
            yield pos, attrs, rect

    def max_atlas_px(self):
        return 8192

    def _raster(self, pos, attrs, rect, size):   # pragma: no cover - interface
        raise NotImplementedError
