"""The numpy z-buffer back end: the reference renderer and the "software method"."""
from __future__ import annotations

import numpy as np

from stages.render.base import N_ATTR, TIE_DEPTH, CutLog, Renderer


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

    def _scan_start(self, size, n_ids, n_bins, log=False):
        H, W = size
        color = np.zeros((H * W, 4), np.float32)
        color[:, 0] = -1
        self._scan = dict(size=size, z=np.zeros(H * W), color=color, log=[] if log else None)

    def _scan_stock(self, pos, attrs, rect):
        st = self._scan
        W = st["size"][1]
        z = st["z"]
        for tt, pix, d, w1f, w2f in self._fragments(pos, rect, W):
            np.maximum.at(z, pix, d)          # farthest stock face: the top of the material
        # pixels without stock keep depth 0: nothing is in front of it, nothing is cut there

    def _scan_draw(self, pos, attrs, rect, counts, b_max, n_bins, log=True):
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
        if log and st["log"] is not None:
            st["log"].append(CutLog(pix.astype(np.int64), ident.astype(np.int32), a[:, N_ATTR].astype(np.float32)))
        cnt = ident >= 0
        b = np.clip((a[:, 1] * n_bins).astype(np.int64), 0, n_bins - 1)
        np.add.at(counts, (ident[cnt], b[cnt]), 1)
        np.maximum.at(b_max, ident[cnt], a[cnt, 2])
        # the last passing fragment of each pixel is its nearest: it is what the buffer keeps
        last = np.ones(len(pix), bool)
        last[:-1] = pix[1:] != pix[:-1]
        ps = pix[last]
        st["z"][ps] = d[last]
        st["color"][ps] = a[last][:, [0, 2, 3, N_ATTR]]       # id, b, c, depth

    def _scan_log(self):
        st = self._scan
        out = CutLog.concat(st["log"])
        st["log"] = []
        return out

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
    full = attrs[t, 0] * (1 - w1 - w2) + attrs[t, 1] * w1 + attrs[t, 2] * w2
    color[hit] = full[:, [0, 1, 2, N_ATTR]]                  # id, a, b, depth
    return color.reshape(H, W, 4)
