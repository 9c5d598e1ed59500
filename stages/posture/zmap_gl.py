"""The z-map by moderngl on the product's headless EGL context (:func:`stages.render.gl.gl_context`).

The inverse offset is uploaded once (vertices relative to its centre, float32, and an index
buffer); a window is one draw of those buffers into its viewport of an atlas framebuffer, with the
orientation's frame as uniforms. The fragment shader writes the generating face from
``gl_PrimitiveID`` (the first ``n_faces`` triangles are the part's faces) and the depth; one read
of the atlas per batch of windows (packed as :func:`stages.render.base._pack` packs the product's).
"""
from __future__ import annotations

import numpy as np

from stages.posture.offset import OffsetMesh, decode
from stages.render.base import _pack

_VS = """
#version 330
uniform vec3 right;
uniform vec3 up;
uniform vec3 dir;
uniform vec3 centre;
uniform vec2 half_px;
uniform float ppm;
uniform float near;
uniform float far;
in vec3 in_pos;
out float v_depth;
void main() {
    vec3 p = in_pos - centre;
    float d = dot(p, dir);
    v_depth = d;
    gl_Position = vec4(dot(p, right) * ppm / half_px.x, dot(p, up) * ppm / half_px.y,
                       2.0 * (d - near) / (far - near) - 1.0, 1.0);
}
"""

_FS = """
#version 330
uniform int n_faces;
in float v_depth;
out vec2 f_out;
void main() {
    f_out = vec2(gl_PrimitiveID < n_faces ? float(gl_PrimitiveID + 1) : 0.0, v_depth);
}
"""


class GLZmap:
    """The inverse offset on the GPU (llvmpipe without one), ready to render windows."""

    atlas_px = 2048

    def __init__(self, offset: OffsetMesh):
        import moderngl
        from stages.render.gl import gl_context
        self._mgl = moderngl
        self.ctx = gl_context()
        self.prog = self.ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        self.origin = 0.5 * (offset.vertices.min(0) + offset.vertices.max(0))
        self.vbo = self.ctx.buffer((offset.vertices - self.origin).astype(np.float32).tobytes())
        self.ibo = self.ctx.buffer(offset.faces.astype(np.int32).tobytes())
        self.vao = self.ctx.vertex_array(self.prog, [(self.vbo, "3f", "in_pos")], index_buffer=self.ibo,
                                         index_element_size=4)
        self.prog["n_faces"].value = int(offset.n_faces)
        self._fbo, self._size = None, 0

    def release(self):
        for o in (self.vao, self.vbo, self.ibo, self._fbo):
            if o is not None:
                o.release()
        if self._fbo is not None:
            self._color.release()
            self._depth.release()
        self._fbo = None

    def _framebuffer(self, size):
        if self._fbo is None or self._size < size:
            if self._fbo is not None:
                self._fbo.release()
                self._color.release()
                self._depth.release()
            self._color = self.ctx.texture((size, size), 2, dtype="f4")
            self._depth = self.ctx.depth_renderbuffer((size, size))
            self._fbo = self.ctx.framebuffer([self._color], self._depth)
            self._size = size
        return self._fbo

    def zmaps(self, views):
        """Yields (i, depth (h, w) mm, +inf where empty; ids (h, w)) for each view, in order."""
        views = list(views)
        if not views:
            return
        atlas = max(self.atlas_px, max(max(v.shape) for v in views))
        fbo = self._framebuffer(atlas)
        offs = _pack(views, atlas)
        mgl, prog = self._mgl, self.prog
        i = 0
        while i < len(views):
            j = i
            while j < len(views) and offs[j][0] == offs[i][0]:
                j += 1
            W = max(offs[n][1] + views[n].shape[1] for n in range(i, j))
            H = max(offs[n][2] + views[n].shape[0] for n in range(i, j))
            fbo.use()
            fbo.clear(red=-1.0, green=0.0, depth=1.0, viewport=(0, 0, W, H))
            self.ctx.disable(mgl.CULL_FACE | mgl.BLEND)
            self.ctx.enable(mgl.DEPTH_TEST)
            self.ctx.depth_func = "<"
            for n in range(i, j):
                v = views[n]
                h, w = v.shape
                right, up, d = v.basis()
                prog["right"].value, prog["up"].value, prog["dir"].value = tuple(right), tuple(up), tuple(d)
                prog["centre"].value = tuple(np.asarray(v.center, float) - self.origin)
                prog["half_px"].value = (w / 2.0, h / 2.0)
                prog["ppm"].value = float(v.px_per_mm)
                prog["near"].value, prog["far"].value = float(v.near_mm), float(v.far_mm)
                fbo.viewport = (offs[n][1], offs[n][2], w, h)
                self.vao.render(mgl.TRIANGLES)
            raw = fbo.read(viewport=(0, 0, W, H), components=2, dtype="f4")
            color = np.frombuffer(raw, np.float32).reshape(H, W, 2)
            for n in range(i, j):
                h, w = views[n].shape
                x0, y0 = offs[n][1], offs[n][2]
                blk = color[y0:y0 + h, x0:x0 + w]
                ids = decode(np.rint(blk[..., 0]))
                depth = np.where(blk[..., 0] < -0.5, np.inf, blk[..., 1].astype(np.float64))
                yield n, depth, ids
            i = j
