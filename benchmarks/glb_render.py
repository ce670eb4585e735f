"""Headless OpenGL render of a ctgs .glb (textured quads) from a ctgs camera, for benchmarks/export_formats.py.

moderngl on an EGL context (Mesa's llvmpipe where there is no GPU: `pip install moderngl`, needs libEGL).
The glb is read with ctgs.formats.gltf.read_glb (pygltflib) and drawn as a glTF viewer draws it: unlit base
colour texture (LINEAR filtering, no mipmaps, as the file's sampler says), alpha blending
(src_alpha, one_minus_src_alpha), no depth test, double-sided, plus one thing a plain viewer does not do:
quads sorted back to front by their centre's camera depth for every view (splat viewers sort; three.js
sorts objects, not the triangles inside one mesh, so there the result depends on buffer order).

Two colour pipelines:
- "image": texture values blended as stored (what our renderer does: it composites image-space colours);
- "linear": an sRGB-correct viewer (three.js with outputColorSpace = sRGB, Blender): the sRGB base colour
  texture is decoded to linear before filtering, blended in linear, and the result encoded back to sRGB.
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.formats.gltf import GlbModel
from ctgs.render.camera import Camera

GL_SRGB8_ALPHA8 = 0x8C43
FAR = 1e4  # world units; only the near plane matters (no depth test), the far one must just contain the scene

VERTEX = """
#version 330
uniform mat4 view;   // world -> camera (OpenCV: x right, y down, z forward)
uniform vec4 intr;   // 2 fx / W, 2 fy / H, 2 cx / W - 1, 2 cy / H - 1
uniform vec2 depth;  // near, far
in vec3 position;
in vec2 uv;
out vec2 v_uv;
void main() {
    vec4 c = view * vec4(position, 1.0);
    float n = depth.x, f = depth.y;
    // NDC y = 2 y_pixel / H - 1 (no flip): framebuffer row 0 is then image row 0.
    gl_Position = vec4(intr.x * c.x + intr.z * c.z, intr.y * c.y + intr.w * c.z,
                       (f + n) / (f - n) * c.z - 2.0 * f * n / (f - n), c.z);
    v_uv = uv;
}
"""
FRAGMENT = """
#version 330
uniform sampler2D atlas;
in vec2 v_uv;
out vec4 colour;
void main() { colour = texture(atlas, v_uv); }
"""


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


class GlbRenderer:
    """Holds the GL context, the quads and one texture per atlas page; `render(camera)` -> [H, W, 3]."""

    def __init__(self, glb: GlbModel, pipeline: str = "image") -> None:
        import moderngl

        if pipeline not in ("image", "linear"):
            raise ValueError(f"pipeline must be 'image' or 'linear', got {pipeline!r}")
        self.pipeline = pipeline
        self.ctx = moderngl.create_context(standalone=True, backend="egl")
        self.prog = self.ctx.program(vertex_shader=VERTEX, fragment_shader=FRAGMENT)
        self.positions = np.concatenate([p.positions for p in glb.pages]).astype(np.float32)  # [Q, 4, 3]
        uvs = np.concatenate([p.uvs for p in glb.pages]).astype(np.float32)  # [Q, 4, 2]
        self.page = np.concatenate([np.full(len(p.positions), i) for i, p in enumerate(glb.pages)])  # [Q]
        self.centres = self.positions.mean(1)  # [Q, 3]
        fmt = GL_SRGB8_ALPHA8 if pipeline == "linear" else None
        self.textures = []
        for p in glb.pages:
            h, w = p.image.shape[:2]
            tex = self.ctx.texture((w, h), 4, np.ascontiguousarray(p.image).tobytes(), internal_format=fmt)
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = False
            self.textures.append(tex)
        vbo = self.ctx.buffer(np.concatenate([self.positions, uvs], 2).reshape(-1, 5).tobytes())
        self.ibo = self.ctx.buffer(reserve=max(4, len(self.positions) * 6 * 4))
        self.vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 2f", "position", "uv")], index_buffer=self.ibo,
                                         index_element_size=4)

    def render(self, camera: Camera, background=(0.0, 0.0, 0.0)) -> torch.Tensor:
        import moderngl

        w, h = camera.width, camera.height
        view = camera.viewmat.detach().cpu().double().numpy()
        depth = self.centres @ view[:3, :3].T[:, 2] + view[2, 3]  # [Q] camera-space z of the quad centres
        keep = np.nonzero(depth >= camera.near)[0]  # the renderer's culling rule (centre before the near plane)
        order = keep[np.argsort(-depth[keep], kind="stable")]  # back to front
        tri = (order[:, None] * 4 + np.array([0, 1, 2, 0, 2, 3])).astype(np.uint32)  # [Q', 6]
        self.ibo.orphan(max(4, tri.nbytes))
        self.ibo.write(tri.tobytes())
        fbo = self.ctx.framebuffer(color_attachments=[self.ctx.texture((w, h), 4, dtype="f4")])
        fbo.use()
        bg = srgb_to_linear(np.asarray(background)) if self.pipeline == "linear" else np.asarray(background)
        fbo.clear(*[float(c) for c in bg], 0.0)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = (moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA, moderngl.ONE,
                               moderngl.ONE_MINUS_SRC_ALPHA)
        self.prog["view"].write(view.T.astype(np.float32).tobytes())  # GLSL matrices are column-major
        self.prog["intr"].value = (2 * camera.fx / w, 2 * camera.fy / h, 2 * camera.cx / w - 1, 2 * camera.cy / h - 1)
        self.prog["depth"].value = (camera.near, FAR)
        # Runs of consecutive quads on one atlas page: one draw call each, in the sorted order.
        pages = self.page[order]
        cuts = np.concatenate([[0], np.nonzero(np.diff(pages))[0] + 1, [len(order)]])
        for a, b in zip(cuts[:-1], cuts[1:]):
            if b > a:
                self.textures[int(pages[a])].use(0)
                self.vao.render(moderngl.TRIANGLES, vertices=6 * int(b - a), first=6 * int(a))
        rgba = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32).reshape(h, w, 4)
        fbo.color_attachments[0].release()
        fbo.release()
        rgb = rgba[..., :3].astype(np.float64)
        if self.pipeline == "linear":
            rgb = linear_to_srgb(rgb)
        return torch.from_numpy(np.clip(rgb, 0.0, 1.0))
