"""Render core: orthographic depth-tested rendering of many small windows at once.

One small interface, two back ends (DESIGN §2):

- ``GLRenderer``: moderngl on a headless EGL context (Mesa llvmpipe on a machine without GPU,
  the GPU on a workstation). The context is created lazily, once per process.
- ``CPURenderer``: a vectorised numpy z-buffer. Reference in tests and the "software method" of the
  speed comparison (bench/bench_render.py).

Both take the same input: a list of :class:`View` windows and one triangle list whose triangles
name the window they belong to. The shared front end (:func:`_to_atlas`) packs the windows into
an atlas framebuffer (many windows per framebuffer: one draw call renders all of them), transforms
every triangle into atlas pixel coordinates, applies per-triangle depth bias and drops triangles
outside their window. The back ends only rasterise: depth test LESS, per-corner attributes
interpolated linearly, fragments outside the triangle's own window rectangle discarded. Memory is
bounded by the atlas size and the triangle budget per draw, never by the size of the program.

A view looks along ``view_dir`` (from below: ``+Z``, the material side; seed para 0045). Depth
is the coordinate along ``view_dir`` measured from the view centre; nearer = smaller.

Besides this one-pass render, :meth:`Renderer.scan` draws a tile's triangles strictly in order
(the stock, then the sweeps pass after pass) and reports per id the fragments that passed the depth
test: what each pass cut (claim 7), the final surface with the pass that left each pixel (claim 8),
and snapshots of the depth buffer mid-scan (the material before a prediction point, claim 5).

Per pixel the result holds the winning triangle's ``id`` (first attribute, an integer stored as
float: exact up to 2**24) and two interpolated attributes ``a``, ``b`` (e.g. rotation angle φ and
contact angle q, claim 4), and the depth.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

ATLAS_PX = 2048                 # default atlas side (grown up to the GL limit for large windows)
TRI_BUDGET = 1_500_000          # triangles per draw (bounds the vertex buffer to ~200 MB)
TIE_DEPTH = 1e-9                # depth (0..1 of the view's range) below which the scan sees a tie


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


@dataclass
class Scene:
    """Triangles for a batch of windows.

    tris : (n, 3, 3) world corners (mm). attrs : (n, 3, 3) per-corner (id, a, b).
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
            return Scene(np.zeros((0, 3, 3)), np.zeros((0, 3, 3), np.float32), np.zeros(0),
                         np.zeros(0, np.int64))
        return Scene(np.concatenate([p.tris for p in parts]),
                     np.concatenate([p.attrs for p in parts]),
                     np.concatenate([p.bias for p in parts]),
                     np.concatenate([p.window for p in parts]))


def make_scene(tris, window, tri_id, a=None, b=None, bias=0.0):
    """Scene from triangles with one id per triangle and per-corner attributes a, b."""
    tris = np.asarray(tris, float).reshape(-1, 3, 3)
    n = len(tris)
    attrs = np.zeros((n, 3, 3), np.float32)
    attrs[:, :, 0] = np.broadcast_to(np.asarray(tri_id, float).reshape(-1, 1) if np.ndim(tri_id)
                                     else tri_id, (n, 3))
    if a is not None:
        attrs[:, :, 1] = np.broadcast_to(a, (n, 3))
    if b is not None:
        attrs[:, :, 2] = np.broadcast_to(b, (n, 3))
    return Scene(tris, attrs, np.broadcast_to(np.asarray(bias, float), (n,)).copy(),
                 np.broadcast_to(np.asarray(window), (n,)).astype(np.int64))


# ------------------------------------------------------------------------------------ front end

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
    """Atlas-space vertices: (n, 3, 3) [x_px, y_px, depth01], attrs+depth (n, 3, 4), rect (n, 4).

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
    attrs = np.empty((len(pos), 3, 4), np.float32)
    attrs[..., :3] = scene.attrs[keep]
    attrs[..., 3] = xyz[..., 2]
    return pos, attrs, rect.astype(np.float64), scene.window[keep]


@dataclass
class ScanResult:
    """Result of :meth:`Renderer.scan`.

    counts : (n_ids, n_bins) fragments of each id that passed the depth test, by bin of ``a``.
    b_max : (n_ids,) largest ``b`` among them (-inf where none passed).
    final : the final image (id -1 where no counted triangle is the last passing fragment).
    snapshots : depth (mm along the view) over each :class:`Snapshot` rectangle, in order.
    """

    counts: np.ndarray
    b_max: np.ndarray
    final: Image
    snapshots: list


@dataclass(frozen=True)
class Snapshot:
    """Marker in the batches of :meth:`Renderer.scan`: read the depth over these pixels now."""

    row0: int
    col0: int
    rows: int
    cols: int


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

    def scan(self, view, stock: Scene, batches, n_ids: int, n_bins: int = 20,
             on_snapshot=None) -> "ScanResult":
        """Ordered depth scan of one window: claims 7 and 8 in one render.

        The stock is drawn first (its top surface: the farthest stock face, so pixels off the
        stock can never be cut), then the triangles of ``batches`` strictly in their order with
        the depth test LESS and depth writes, as the machine removes material pass after pass.
        A fragment passes where it is nearer than the stock and everything drawn before it: for
        a sweep that is where the pass cuts. Per id (attribute 0, ``>= 0``; negative ids are
        drawn but not counted) the scan counts passing fragments in ``n_bins`` bins of attribute
        ``a`` (in [0, 1], e.g. the position along the pass) and keeps the largest attribute ``b``
        (e.g. the contact angle). The returned image holds, per pixel, the last passing fragment:
        the final surface and which id left it.

        Memory is bounded by the window and the triangle budget per draw: ``batches`` is any
        iterable of scenes (e.g. a generator over pass ranges), each split into draws. A
        :class:`Snapshot` among them records the depth buffer (mm along the view, ``near_mm``
        where nothing is) over its pixel rectangle at that point of the scan: the material left
        at that moment (``ScanResult.snapshots``, in order; or passed to ``on_snapshot(depth)``
        as it is taken, so that memory does not grow with the number of snapshots).
        """
        h, w = view.shape
        if max(h, w) > self.max_atlas_px():
            raise ValueError(f"scan window {w}x{h} px larger than {self.max_atlas_px()}")
        offs = [(0, 0, 0)]
        counts = np.zeros((n_ids, n_bins), np.int64)
        b_max = np.full(n_ids, -np.inf)
        snaps = []
        self._scan_start((h, w), n_ids, n_bins)
        try:
            pos, attrs, rect, _ = _to_atlas([view], stock, offs)
            self._scan_stock(pos, attrs, rect)
            for sc in batches:
                if isinstance(sc, Snapshot):
                    r0, c0 = sc.row0, sc.col0
                    d01 = self._scan_depth(r0, c0, sc.rows, sc.cols)
                    (on_snapshot or snaps.append)(d01 * (view.far_mm - view.near_mm) + view.near_mm)
                    continue
                for a in range(0, len(sc.tris), self.tri_budget):
                    part = Scene(sc.tris[a:a + self.tri_budget], sc.attrs[a:a + self.tri_budget],
                                 sc.bias[a:a + self.tri_budget],
                                 np.zeros(min(self.tri_budget, len(sc.tris) - a), np.int64))
                    pos, attrs, rect, _ = _to_atlas([view], part, offs)
                    self._scan_draw(pos, attrs, rect, counts, b_max, n_bins)
        finally:
            color = self._scan_finish(counts, b_max)
        empty = color[..., 0] < -0.5
        depth = np.where(empty, np.inf, color[..., 3].astype(np.float64) + view.near_mm)
        final = Image(view, depth, np.where(empty, -1, np.rint(color[..., 0])).astype(np.int64),
                      color[..., 1].copy(), color[..., 2].copy())
        return ScanResult(counts, b_max, final, snaps)

    def max_atlas_px(self):
        return 8192

    def _raster(self, pos, attrs, rect, size):   # pragma: no cover - interface
        raise NotImplementedError


# ------------------------------------------------------------------------------------ numpy z-buffer

class CPURenderer(Renderer):
    """Vectorised numpy z-buffer over the same atlas triangles as the GL back end.

    Triangles are bucketed by bounding-box size; each bucket is rasterised as one array
    operation (pixel centres × edge functions), and fragments are merged into the z-buffer by a
    sort per chunk. Memory is bounded by ``frag_budget``.
    """

    name = "cpu"
    frag_budget = 2_000_000

    def _fragments(self, pos, rect, W):
        """Fragments of the atlas triangles ``pos``: yields (tri, pix, depth, w1, w2) per chunk.

        Pixel centres (i + 0.5) inside a triangle (edge functions, inclusive) and inside its
        window rectangle, with depth in [0, 1]. Chunks hold at most ``frag_budget`` candidates.
        """
        if not len(pos):
            return
        x, y, z = pos[..., 0].astype(np.float64), pos[..., 1].astype(np.float64), pos[..., 2]
        area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
        ok = np.abs(area2) > 1e-12
        # pixel centres (i + 0.5) covered by the bbox, clipped to the triangle's window
        x_lo = np.maximum(np.ceil(x.min(1) - 0.5), rect[:, 0]).astype(np.int64)
        x_hi = np.minimum(np.floor(x.max(1) - 0.5), rect[:, 2] - 1).astype(np.int64)
        y_lo = np.maximum(np.ceil(y.min(1) - 0.5), rect[:, 1]).astype(np.int64)
        y_hi = np.minimum(np.floor(y.max(1) - 0.5), rect[:, 3] - 1).astype(np.int64)
        ok &= (x_hi >= x_lo) & (y_hi >= y_lo)
        idx = np.nonzero(ok)[0]
        bw = x_hi[idx] - x_lo[idx] + 1
        bh = y_hi[idx] - y_lo[idx] + 1
        kw = np.ceil(np.log2(bw)).astype(np.int64)
        kh = np.ceil(np.log2(bh)).astype(np.int64)
        key = kw * 64 + kh
        # edge-function coefficients: w_k = a_k*px + b_k*py + c_k  (k = 1, 2)
        inv = 1.0 / np.where(ok, area2, 1.0)
        a1 = (y[:, 2] - y[:, 0]) * inv
        b1 = -(x[:, 2] - x[:, 0]) * inv
        a2 = -(y[:, 1] - y[:, 0]) * inv
        b2 = (x[:, 1] - x[:, 0]) * inv
        for kk in np.unique(key):
            tri = idx[key == kk]
            BW, BH = 1 << int(kk // 64), 1 << int(kk % 64)
            per = max(1, self.frag_budget // (BW * BH))
            ox = np.arange(BW)[None, None, :]
            oy = np.arange(BH)[None, :, None]
            for s in range(0, len(tri), per):
                t = tri[s:s + per]
                px = x_lo[t][:, None, None] + ox
                py = y_lo[t][:, None, None] + oy
                dx = px + 0.5 - x[t, 0][:, None, None]
                dy = py + 0.5 - y[t, 0][:, None, None]
                w1 = a1[t][:, None, None] * dx + b1[t][:, None, None] * dy
                w2 = a2[t][:, None, None] * dx + b2[t][:, None, None] * dy
                m = ((w1 >= -1e-9) & (w2 >= -1e-9) & (w1 + w2 <= 1 + 1e-9)
                     & (px <= x_hi[t][:, None, None]) & (py <= y_hi[t][:, None, None]))
                ti, iy, ix = np.nonzero(m)
                if not len(ti):
                    continue
                w1f, w2f = w1[ti, iy, ix], w2[ti, iy, ix]
                tt = t[ti]
                d = z[tt, 0] + w1f * (z[tt, 1] - z[tt, 0]) + w2f * (z[tt, 2] - z[tt, 0])
                pix = (y_lo[tt] + iy) * W + (x_lo[tt] + ix)
                inside = (d >= 0) & (d <= 1)
                yield tt[inside], pix[inside], d[inside], w1f[inside], w2f[inside]

    def _raster(self, pos, attrs, rect, size):
        H, W = size
        zbuf = np.full(H * W, np.inf)
        tbuf = np.full(H * W, -1, np.int64)
        w1buf = np.zeros(H * W)
        w2buf = np.zeros(H * W)
        for tt, pix, d, w1f, w2f in self._fragments(pos, rect, W):
            # nearest fragment per pixel within the chunk, then merge with the buffer
            o = np.lexsort((tt, d, pix))
            ps = pix[o]
            first = np.ones(len(o), bool)
            first[1:] = ps[1:] != ps[:-1]
            o = o[first]
            ps = pix[o]
            win = d[o] < zbuf[ps]
            o, ps = o[win], ps[win]
            zbuf[ps] = d[o]
            tbuf[ps] = tt[o]
            w1buf[ps] = w1f[o]
            w2buf[ps] = w2f[o]
        return _interpolate(attrs, tbuf, w1buf, w2buf, H, W)

    def _scan_start(self, size, n_ids, n_bins):
        H, W = size
        color = np.zeros((H * W, 4), np.float32)
        color[:, 0] = -1
        self._scan = dict(size=size, z=np.zeros(H * W), color=color)

    def _scan_stock(self, pos, attrs, rect):
        st = self._scan
        W = st["size"][1]
        z = st["z"]
        for tt, pix, d, w1f, w2f in self._fragments(pos, rect, W):
            np.maximum.at(z, pix, d)          # farthest stock face: the top of the material
        # pixels without stock keep depth 0: nothing is in front of it, nothing is cut there

    def _scan_draw(self, pos, attrs, rect, counts, b_max, n_bins):
        st = self._scan
        W = st["size"][1]
        frags = list(self._fragments(pos, rect, W))
        if not frags:
            return
        tt, pix, d, w1f, w2f = (np.concatenate(c) for c in zip(*frags))
        # draw order = triangle order: per pixel, a fragment passes the depth test LESS when it
        # is nearer than the buffer and than every earlier fragment of this batch there
        o = np.lexsort((tt, pix))
        tt, pix, d, w1f, w2f = tt[o], pix[o], d[o], w1f[o], w2f[o]
        first = np.ones(len(pix), bool)
        first[1:] = pix[1:] != pix[:-1]
        seg = np.cumsum(first)
        run = np.minimum.accumulate(d - 2.0 * seg) + 2.0 * seg     # running min per pixel
        prev = np.empty_like(run)
        prev[1:] = run[:-1]
        prev[first] = np.inf
        # ties (the same surface drawn again by other triangles) do not pass: float64 round-off
        # between coplanar triangles is far below TIE_DEPTH (GL's fixed-point depth ties exactly)
        ok = d < np.minimum(prev, st["z"][pix]) - TIE_DEPTH
        tt, pix, d, w1f, w2f = tt[ok], pix[ok], d[ok], w1f[ok], w2f[ok]
        if not len(tt):
            return
        a = attrs[tt, 0] * (1 - w1f - w2f)[:, None] + attrs[tt, 1] * w1f[:, None] + attrs[tt, 2] * w2f[:, None]
        ident = np.rint(a[:, 0]).astype(np.int64)
        cnt = ident >= 0
        b = np.clip((a[:, 1] * n_bins).astype(np.int64), 0, n_bins - 1)
        np.add.at(counts, (ident[cnt], b[cnt]), 1)
        np.maximum.at(b_max, ident[cnt], a[cnt, 2])
        # the last passing fragment of each pixel is its nearest: it is what the buffer keeps
        last = np.ones(len(pix), bool)
        last[:-1] = pix[1:] != pix[:-1]
        ps = pix[last]
        st["z"][ps] = d[last]
        st["color"][ps] = a[last]

    def _scan_depth(self, r0, c0, rows, cols):
        H, W = self._scan["size"]
        return self._scan["z"].reshape(H, W)[r0:r0 + rows, c0:c0 + cols].copy()

    def _scan_finish(self, counts, b_max):
        st, self._scan = self._scan, None
        H, W = st["size"]
        return st["color"].reshape(H, W, 4)


def _interpolate(attrs, tbuf, w1buf, w2buf, H, W):
    """Colour buffer (H, W, 4) from the winning triangle and barycentrics per pixel (-1: none)."""
    color = np.zeros((H * W, 4), np.float32)
    color[:, 0] = -1
    hit = np.nonzero(tbuf >= 0)[0]
    t = tbuf[hit]
    w1, w2 = w1buf[hit, None], w2buf[hit, None]
    color[hit] = attrs[t, 0] * (1 - w1 - w2) + attrs[t, 1] * w1 + attrs[t, 2] * w2
    return color.reshape(H, W, 4)


# ------------------------------------------------------------------------------------ moderngl

_GL_CONTEXT = None
_GL_ERROR = None

_VS = """
#version 330
uniform vec2 size;
in vec3 in_pos;
in vec4 in_attr;
in vec4 in_rect;
out vec4 v_attr;
void main() {
    gl_Position = vec4(in_pos.x / size.x * 2.0 - 1.0, in_pos.y / size.y * 2.0 - 1.0,
                       in_pos.z * 2.0 - 1.0, 1.0);
    v_attr = in_attr;
    // clip to the triangle's own window of the atlas (clip planes keep early depth testing)
    gl_ClipDistance[0] = in_pos.x - in_rect.x;
    gl_ClipDistance[1] = in_rect.z - in_pos.x;
    gl_ClipDistance[2] = in_pos.y - in_rect.y;
    gl_ClipDistance[3] = in_rect.w - in_pos.y;
}
"""

_FS = """
#version 330
in vec4 v_attr;
out vec4 f_color;
void main() {
    f_color = v_attr;
}
"""


_SCAN_VS = _VS.replace("#version 330", "#version 430")

_SCAN_FS = """
#version 430
layout(early_fragment_tests) in;          // only fragments that pass the depth test run this
layout(std430, binding = 0) buffer Counts { uint counts[]; };
layout(std430, binding = 1) buffer BMax { int bmax[]; };
uniform int n_bins;
uniform int stock;
in vec4 v_attr;
out vec4 f_color;
void main() {
    if (stock == 1) {
        f_color = vec4(-1.0, 0.0, 0.0, 0.0);
        return;
    }
    int ident = int(floor(v_attr.x + 0.5));
    if (ident >= 0) {
        int bin = clamp(int(v_attr.y * float(n_bins)), 0, n_bins - 1);
        atomicAdd(counts[ident * n_bins + bin], 1u);
        atomicMax(bmax[ident], int(round(v_attr.z * 1000.0)));
    }
    f_color = v_attr;
}
"""
B_SCALE = 1000.0                      # GL keeps b_max as an integer in thousandths


def gl_context():
    """The process-wide headless EGL context (created on first use). Raises if none opens."""
    global _GL_CONTEXT, _GL_ERROR
    if _GL_CONTEXT is None:
        if _GL_ERROR is not None:
            raise RuntimeError(_GL_ERROR)
        try:
            import moderngl
            _GL_CONTEXT = moderngl.create_context(standalone=True, backend="egl")
        except Exception as e:  # no libEGL, no device, driver refuses...
            _GL_ERROR = f"cannot open a headless EGL context: {type(e).__name__}: {e}"
            raise RuntimeError(_GL_ERROR) from None
    return _GL_CONTEXT


class GLRenderer(Renderer):
    """moderngl back end. All windows of a draw share one float framebuffer (the atlas)."""

    name = "gl"

    def __init__(self):
        import moderngl
        self._mgl = moderngl
        self.ctx = gl_context()
        self.prog = self.ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        self._scan_prog = None
        self._fbo, self._fbo_size = None, None

    def max_atlas_px(self):
        return min(8192, int(self.ctx.info.get("GL_MAX_TEXTURE_SIZE", 8192)))

    def _framebuffer(self, size):
        H, W = size
        need = (max(W, 256), max(H, 256))
        if self._fbo is None or self._fbo_size[0] < need[0] or self._fbo_size[1] < need[1]:
            if self._fbo is not None:
                self._fbo.release()
                self._color.release()
                self._depth.release()
            sz = (max(need[0], self._fbo_size[0] if self._fbo_size else 0),
                  max(need[1], self._fbo_size[1] if self._fbo_size else 0))
            self._color = self.ctx.texture(sz, 4, dtype="f4")
            self._depth = self.ctx.depth_renderbuffer(sz)
            self._fbo = self.ctx.framebuffer([self._color], self._depth)
            self._fbo_size = sz
        return self._fbo

    def _begin(self, size, depth_clear):
        H, W = size
        mgl = self._mgl
        fbo = self._framebuffer(size)
        fbo.use()
        fbo.viewport = (0, 0, W, H)
        self.ctx.disable(mgl.CULL_FACE | mgl.BLEND)
        self.ctx.enable(mgl.DEPTH_TEST)
        for i in range(4):
            self.ctx.enable_direct(0x3000 + i)          # GL_CLIP_DISTANCE0..3
        fbo.clear(red=-1.0, green=0.0, blue=0.0, alpha=0.0, depth=depth_clear, viewport=(0, 0, W, H))
        return fbo

    def _draw(self, prog, pos, attrs, rect, size):
        if not len(pos):
            return
        H, W = size
        n = len(pos)
        data = np.empty((n, 3, 11), np.float32)
        data[..., 0:3] = pos
        data[..., 3:7] = attrs
        data[..., 7:11] = rect[:, None, :]
        vbo = self.ctx.buffer(data.tobytes())
        vao = self.ctx.vertex_array(prog, [(vbo, "3f 4f 4f", "in_pos", "in_attr", "in_rect")])
        prog["size"].value = (float(W), float(H))
        vao.render(self._mgl.TRIANGLES)
        vao.release()
        vbo.release()

    def _read(self, fbo, size):
        H, W = size
        raw = fbo.read(viewport=(0, 0, W, H), components=4, dtype="f4")
        return np.frombuffer(raw, np.float32).reshape(H, W, 4).copy()

    def _raster(self, pos, attrs, rect, size):
        fbo = self._begin(size, 1.0)
        self.ctx.depth_func = "<"
        self._draw(self.prog, pos, attrs, rect, size)
        return self._read(fbo, size)

    def _scan_start(self, size, n_ids, n_bins):
        if self._scan_prog is None:
            self._scan_prog = self.ctx.program(vertex_shader=_SCAN_VS, fragment_shader=_SCAN_FS)
        fbo = self._begin(size, 0.0)                  # off the stock nothing can pass
        counts = self.ctx.buffer(reserve=max(4, 4 * n_ids * n_bins))
        counts.clear()
        bmax = self.ctx.buffer(np.full(max(1, n_ids), np.iinfo(np.int32).min, np.int32).tobytes())
        counts.bind_to_storage_buffer(0)
        bmax.bind_to_storage_buffer(1)
        self._scan_prog["n_bins"].value = int(n_bins)
        self._scan = dict(fbo=fbo, size=size, counts=counts, bmax=bmax, n=(n_ids, n_bins))

    def _scan_stock(self, pos, attrs, rect):
        self.ctx.depth_func = ">"                     # farthest stock face: top of the material
        self._scan_prog["stock"].value = 1
        self._draw(self._scan_prog, pos, attrs, rect, self._scan["size"])

    def _scan_draw(self, pos, attrs, rect, counts, b_max, n_bins):
        self.ctx.depth_func = "<"
        self._scan_prog["stock"].value = 0
        self._draw(self._scan_prog, pos, attrs, rect, self._scan["size"])

    def _scan_depth(self, r0, c0, rows, cols):
        raw = self._scan["fbo"].read(viewport=(c0, r0, cols, rows), components=1, attachment=-1,
                                     dtype="f4")
        return np.frombuffer(raw, np.float32).reshape(rows, cols).astype(np.float64)

    def _scan_finish(self, counts, b_max):
        st, self._scan = self._scan, None
        color = self._read(st["fbo"], st["size"])
        n_ids, n_bins = st["n"]
        if n_ids:
            counts += np.frombuffer(st["counts"].read(), np.uint32)[:n_ids * n_bins].reshape(n_ids, n_bins)
            bm = np.frombuffer(st["bmax"].read(), np.int32)[:n_ids]
            b_max[:] = np.where(bm == np.iinfo(np.int32).min, -np.inf, bm / B_SCALE)
        st["counts"].release()
        st["bmax"].release()
        return color


_RENDERERS = {}


def make_renderer(backend: str = "auto") -> Renderer:
    """Renderer for ``render.backend``: ``"gl"``, ``"cpu"`` or ``"auto"``.

    ``auto`` uses gl when a headless EGL context opens and falls back to cpu otherwise, logging
    why. ``gl`` raises RuntimeError when no context opens. Renderers are cached per process.
    """
    if backend not in ("auto", "gl", "cpu"):
        from stages import InputError
        raise InputError(f"render.backend: {backend!r} is not one of auto, gl, cpu")
    if backend in _RENDERERS:
        return _RENDERERS[backend]
    if backend == "cpu":
        r = CPURenderer()
    elif backend == "gl":
        r = GLRenderer()
    else:
        try:
            r = make_renderer("gl")
        except Exception as e:
            log.warning("render.backend auto: using the cpu back end (%s)", e)
            r = make_renderer("cpu")
    _RENDERERS[backend] = r
    return r
