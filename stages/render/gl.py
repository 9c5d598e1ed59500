"""The moderngl back end: headless EGL (Mesa's llvmpipe where there is no GPU)."""
from __future__ import annotations

import numpy as np

from stages.render.base import CutLog, Renderer

LOG_PER_PIXEL = 8          # room in the scan's log per pixel of the window, per batch

_GL_CONTEXT = None


_GL_ERROR = None


_VS = """
#version 330
uniform vec2 size;
in vec3 in_pos;
in vec4 in_attr;
in float in_depth;
in vec4 in_rect;
out vec4 v_attr;
out float v_depth;
void main() {
    gl_Position = vec4(in_pos.x / size.x * 2.0 - 1.0, in_pos.y / size.y * 2.0 - 1.0,
                       in_pos.z * 2.0 - 1.0, 1.0);
    v_attr = in_attr;
    v_depth = in_depth;
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
in float v_depth;
out vec4 f_color;
void main() {
    f_color = vec4(v_attr.xyz, v_depth);
}
"""


_SCAN_VS = _VS.replace("#version 330", "#version 430")


_SCAN_FS = """
#version 430
layout(early_fragment_tests) in;          // only fragments that pass the depth test run this
layout(std430, binding = 0) buffer Counts { uint counts[]; };
layout(std430, binding = 1) buffer BMax { int bmax[]; };
layout(std430, binding = 2) buffer Log { uint n_log; uint pad0; uint pad1; uint pad2; uvec4 entries[]; };
uniform int n_bins;
uniform int stock;
uniform int log_cap;       // entries the log holds (0: no log)
uniform int width;
in vec4 v_attr;
in float v_depth;
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
    if (log_cap > 0) {
        uint i = atomicAdd(n_log, 1u);
        if (i < uint(log_cap)) {
            uint pix = uint(gl_FragCoord.y) * uint(width) + uint(gl_FragCoord.x);
            entries[i] = uvec4(pix, uint(ident), floatBitsToUint(v_depth), 0u);
        }
    }
    f_color = vec4(v_attr.x, v_attr.z, v_attr.w, v_depth);
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
        data = np.empty((n, 3, 12), np.float32)
        data[..., 0:3] = pos
        data[..., 3:8] = attrs                          # id, a, b, c, depth
        data[..., 8:12] = rect[:, None, :]
        vbo = self.ctx.buffer(data.tobytes())
        vao = self.ctx.vertex_array(prog, [(vbo, "3f 4f 1f 4f", "in_pos", "in_attr", "in_depth", "in_rect")])
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

    def _scan_start(self, size, n_ids, n_bins, log=False):
        if self._scan_prog is None:
            self._scan_prog = self.ctx.program(vertex_shader=_SCAN_VS, fragment_shader=_SCAN_FS)
        H, W = size
        fbo = self._begin(size, 0.0)                  # off the stock nothing can pass
        counts = self.ctx.buffer(reserve=max(4, 4 * n_ids * n_bins))
        counts.clear()
        bmax = self.ctx.buffer(np.full(max(1, n_ids), np.iinfo(np.int32).min, np.int32).tobytes())
        cap = LOG_PER_PIXEL * H * W if log else 0
        logbuf = self.ctx.buffer(reserve=16 + 16 * max(cap, 1))
        logbuf.clear(size=16)
        counts.bind_to_storage_buffer(0)
        bmax.bind_to_storage_buffer(1)
        logbuf.bind_to_storage_buffer(2)
        self._scan_prog["n_bins"].value = int(n_bins)
        self._scan_prog["width"].value = int(W)
        self._scan_prog["log_cap"].value = 0
        self._scan = dict(fbo=fbo, size=size, counts=counts, bmax=bmax, n=(n_ids, n_bins), log=logbuf, cap=cap)

    def _scan_stock(self, pos, attrs, rect):
        self.ctx.depth_func = ">"                     # farthest stock face: top of the material
        self._scan_prog["stock"].value = 1
        self._draw(self._scan_prog, pos, attrs, rect, self._scan["size"])

    def _scan_draw(self, pos, attrs, rect, counts, b_max, n_bins, log=True):
        self.ctx.depth_func = "<"
        self._scan_prog["stock"].value = 0
        self._scan_prog["log_cap"].value = int(self._scan["cap"]) if log else 0
        self._draw(self._scan_prog, pos, attrs, rect, self._scan["size"])

    def _scan_log(self):
        """The entries logged since the last call (the log buffer is then emptied)."""
        st = self._scan
        self.ctx.memory_barrier()                      # the shader's writes before the read
        n = int(np.frombuffer(st["log"].read(size=4), np.uint32)[0])
        if n > st["cap"]:
            raise RuntimeError(f"scan log overflow: {n} fragments passed in one batch, room for {st['cap']} "
                               "(draw fewer sweeps per batch)")
        if n == 0:
            return CutLog.concat([])
        e = np.frombuffer(st["log"].read(size=16 * n, offset=16), np.uint32).reshape(n, 4)
        st["log"].clear(size=16)
        return CutLog(e[:, 0].astype(np.int64), e[:, 1].view(np.int32).copy(), e[:, 2].view(np.float32).copy())

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
        st["log"].release()
        return color
