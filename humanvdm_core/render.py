"""Headless rasterizer for textured meshes (moderngl over EGL; llvmpipe on CPU, the GPU's driver on GPU).

Contract of :func:`render_views` (one :class:`RenderResult` for N cameras, all float32):

- ``rgba`` (N, H, W, 4): unlit albedo (the texture's sRGB values as they are, times vertex
  colours), composited over ``background``; A = the subject's coverage of the pixel.
- ``depth`` (N, H, W): camera-space z (distance along the optical axis), 0 where empty.
- ``normals`` (N, H, W, 3): world-space unit normals of the visible surface, turned towards the
  camera (back faces of open meshes flip), 0 where empty.

Cameras are used exactly as :class:`humanvdm_core.cameras.Cameras` states them (OpenCV axes,
pixel centres at integer + 0.5): a world point X lands in pixel ``floor(K @ (w2c @ X))`` (after the
perspective divide), row index = v (top row first). The GL projection is built from K so that
NDC x = 2u/W - 1 and NDC y = 2v/H - 1; GL's window row r is then image row r, so read-back needs
no flip (winding is mirrored, hence ``front_face='cw'``).

Antialiasing is MSAA (4 samples by default, 1 = none): a resolve pass averages each pixel's
samples; colour is composited over the background by coverage, depth and normals are averaged
over covered samples only (normals renormalised), so silhouettes are soft and never mix in the
background's zeros. Faces are not culled (scans may be open or inconsistently wound). Vertex
normals are area-weighted face normals over vertices merged by position, so UV seams do not show.
The texture is mipmapped (trilinear filtering). One GL context per process is created lazily and
reused (:func:`get_renderer`; creating one costs 0.05-0.4 s); a :class:`Renderer` makes its context
current for each call, so several can coexist. Nothing is drawn in parallel: on llvmpipe the
geometry stage runs on one core and rasterization on all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from humanvdm_core.cameras import Cameras
from humanvdm_core.scans import TexturedMesh

DEFAULT_SAMPLES = 4

_VERTEX_SHADER = """
#version 330
uniform mat4 clip_from_world;
uniform mat4 cam_from_world;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
in vec3 in_color;
centroid out vec3 v_normal;
centroid out vec2 v_uv;
centroid out vec3 v_color;
centroid out float v_depth;
void main() {
    gl_Position = clip_from_world * vec4(in_pos, 1.0);
    v_depth = (cam_from_world * vec4(in_pos, 1.0)).z;
    v_normal = in_normal;
    v_uv = in_uv;
    v_color = in_color;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform sampler2D albedo;
centroid in vec3 v_normal;
centroid in vec2 v_uv;
centroid in vec3 v_color;
centroid in float v_depth;
layout(location = 0) out vec4 out_color;
layout(location = 1) out vec4 out_geometry;
void main() {
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;
    out_color = vec4(texture(albedo, v_uv).rgb * v_color, 1.0);
    out_geometry = vec4(n, v_depth);
}
"""


_FULLSCREEN_SHADER = """
#version 330
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

# Averages the samples of a pixel: colour is premultiplied (background samples are 0), so it is
# composited over the background; depth and normals are averaged over covered samples only.
_RESOLVE_SHADER = """
#version 330
uniform sampler2DMS color_ms;
uniform sampler2DMS geometry_ms;
uniform int samples;
uniform vec3 background;
layout(location = 0) out vec4 out_rgba;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_depth;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 c = vec4(0.0);
    vec4 g = vec4(0.0);
    for (int s = 0; s < samples; ++s) {
        c += texelFetch(color_ms, p, s);
        g += texelFetch(geometry_ms, p, s);
    }
    float alpha = c.a / float(samples);
    out_rgba = vec4(c.rgb / float(samples) + (1.0 - alpha) * background, alpha);
    float len = length(g.xyz);
    out_normal = (c.a > 0.0 && len > 0.0) ? vec4(g.xyz / len, 0.0) : vec4(0.0);
    out_depth = vec4(c.a > 0.0 ? g.w / c.a : 0.0, 0.0, 0.0, 0.0);
}
"""


@dataclass
class RenderResult:
    rgba: np.ndarray  # (N, H, W, 4) float32
    depth: np.ndarray  # (N, H, W) float32
    normals: np.ndarray  # (N, H, W, 3) float32

    def __len__(self) -> int:
        return len(self.rgba)

    @property
    def alpha(self) -> np.ndarray:
        return self.rgba[..., 3]


def gl_projection(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """4x4 clip-from-camera matrix for OpenCV camera coordinates and intrinsics ``K``.

    clip = P @ [x, y, z, 1] with w = z, so NDC x = 2u/W - 1 and NDC y = 2v/H - 1 where
    (u, v) = K @ (x, y, z) / z; NDC z maps [near, far] to [-1, 1].
    """
    fx, s, cx = K[0]
    _, fy, cy = K[1]
    return np.array([
        [2.0 * fx / width, 2.0 * s / width, 2.0 * cx / width - 1.0, 0.0],
        [0.0, 2.0 * fy / height, 2.0 * cy / height - 1.0, 0.0],
        [0.0, 0.0, (far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, 1.0, 0.0],
    ])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, shared by vertices at the same position (seams stay smooth)."""
    v = vertices.astype(np.float64)
    _, inverse = np.unique(vertices, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    n_unique = int(inverse.max()) + 1 if len(inverse) else 0
    tri = v[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    acc = np.zeros((n_unique, 3))
    for corner in range(3):
        idx = inverse[faces[:, corner]]
        for axis in range(3):
            acc[:, axis] += np.bincount(idx, weights=face_n[:, axis], minlength=n_unique)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    acc = np.where(length > 0, acc / np.maximum(length, 1e-30), np.array([0.0, 0.0, 1.0]))
    return acc[inverse].astype(np.float32)


class Renderer:
    """A GL context with the draw and resolve programs; render many meshes and camera sets with it."""

    def __init__(self, samples: int = DEFAULT_SAMPLES):
        import moderngl

        self.ctx = moderngl.create_standalone_context(backend="egl")
        self.samples = max(1, min(int(samples), self.ctx.max_samples))
        self.max_texture_size = int(self.ctx.info["GL_MAX_TEXTURE_SIZE"])
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self.resolve_program = self.ctx.program(vertex_shader=_FULLSCREEN_SHADER, fragment_shader=_RESOLVE_SHADER)
        self.resolve_program["samples"].value = self.samples
        self.resolve_program["color_ms"].value = 1
        self.resolve_program["geometry_ms"].value = 2
        self.fullscreen = self.ctx.vertex_array(self.resolve_program, [])
        self._targets: dict[tuple[int, int], tuple] = {}

    def _framebuffers(self, width: int, height: int) -> tuple:
        """(multisample draw framebuffer, its colour and geometry textures, resolved framebuffer)."""
        key = (width, height)
        if key not in self._targets:
            ctx, size = self.ctx, (width, height)
            color = ctx.texture(size, 4, samples=self.samples, dtype="f4")
            geometry = ctx.texture(size, 4, samples=self.samples, dtype="f4")
            draw = ctx.framebuffer(color_attachments=[color, geometry],
                                   depth_attachment=ctx.depth_renderbuffer(size, samples=self.samples))
            resolved = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, dtype="f4") for _ in range(3)])
            self._targets[key] = (draw, color, geometry, resolved)
        return self._targets[key]

    def render(
        self, mesh: TexturedMesh, cameras: Cameras, background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ) -> RenderResult:
        """Render ``mesh`` from every camera (see the module docstring for the output contract)."""
        with self.ctx:  # make this context current (several renderers may coexist)
            return self._render(mesh, cameras, background)

    def _render(self, mesh: TexturedMesh, cameras: Cameras, background: tuple[float, float, float]) -> RenderResult:
        import moderngl

        ctx = self.ctx
        n, w, h = len(cameras), cameras.width, cameras.height
        rgba = np.empty((n, h, w, 4), dtype=np.float32)
        depth = np.empty((n, h, w), dtype=np.float32)
        normals = np.empty((n, h, w, 3), dtype=np.float32)
        if mesh.num_faces == 0 or n == 0:
            rgba[...] = (*background, 0.0)
            depth[...] = 0.0
            normals[...] = 0.0
            return RenderResult(rgba, depth, normals)

        nv = len(mesh.vertices)
        uvs = mesh.uvs if mesh.uvs is not None else np.zeros((nv, 2), dtype=np.float32)
        colors = mesh.vertex_colors if mesh.vertex_colors is not None else np.ones((nv, 3), dtype=np.float32)
        interleaved = np.concatenate(
            [mesh.vertices, vertex_normals(mesh.vertices, mesh.faces), uvs, colors], axis=1
        ).astype(np.float32)
        texture_image = mesh.texture if mesh.texture is not None else np.full((1, 1, 3), 255, dtype=np.uint8)
        if max(texture_image.shape[:2]) > self.max_texture_size:
            import cv2

            f = self.max_texture_size / max(texture_image.shape[:2])
            size = (max(1, int(texture_image.shape[1] * f)), max(1, int(texture_image.shape[0] * f)))
            texture_image = cv2.resize(texture_image, size, interpolation=cv2.INTER_AREA)
        # GL's first texture row is t = 0, the image's bottom row in the OBJ UV convention.
        texture = ctx.texture((texture_image.shape[1], texture_image.shape[0]), 3,
                              np.ascontiguousarray(texture_image[::-1]).tobytes(), alignment=1)
        texture.build_mipmaps()
        texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        vbo = ctx.buffer(interleaved.tobytes())
        ibo = ctx.buffer(mesh.faces.astype(np.int32).tobytes())
        vao = ctx.vertex_array(self.program, [(vbo, "3f 3f 2f 3f", "in_pos", "in_normal", "in_uv", "in_color")],
                               index_buffer=ibo, index_element_size=4)
        draw, color_ms, geometry_ms, resolved = self._framebuffers(w, h)
        try:
            texture.use(0)
            color_ms.use(1)
            geometry_ms.use(2)
            self.program["albedo"].value = 0
            self.resolve_program["background"].value = tuple(float(c) for c in background)
            ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
            ctx.front_face = "cw"  # image rows go down (see module docstring), which mirrors winding
            centre = mesh.bounds.astype(np.float64).mean(axis=0)
            bound = float(np.linalg.norm(mesh.vertices.astype(np.float64) - centre, axis=1).max()) * 1.01 + 1e-6
            w2c_all = cameras.w2c
            for i in range(n):
                w2c = w2c_all[i]
                d = float((w2c[:3, :3] @ centre + w2c[:3, 3])[2])
                far = max(d + bound, 1e-3)
                near = max(d - bound, far * 1e-4)
                clip = gl_projection(cameras.K[i], w, h, near, far) @ w2c
                self.program["clip_from_world"].write(clip.T.astype(np.float32).tobytes())
                self.program["cam_from_world"].write(w2c.T.astype(np.float32).tobytes())
                draw.use()
                ctx.enable(moderngl.DEPTH_TEST)
                draw.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                vao.render(moderngl.TRIANGLES)
                resolved.use()
                ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
                self.fullscreen.render(moderngl.TRIANGLES, vertices=3)
                resolved.read_into(rgba[i], components=4, attachment=0, dtype="f4")
                resolved.read_into(normals[i], components=3, attachment=1, dtype="f4")
                resolved.read_into(depth[i], components=1, attachment=2, dtype="f4")
        finally:
            for obj in (vao, vbo, ibo, texture):
                obj.release()
        return RenderResult(rgba, depth, normals)

    def release(self) -> None:
        """Free the GL objects and the context; the renderer is unusable afterwards."""
        with self.ctx:
            for draw, _color_ms, _geometry_ms, resolved in self._targets.values():
                for fbo in (draw, resolved):
                    for att in (*fbo.color_attachments, fbo.depth_attachment):
                        if att is not None:
                            att.release()
                    fbo.release()
            self._targets.clear()
            for obj in (self.fullscreen, self.program, self.resolve_program):
                obj.release()
        self.ctx.release()


_RENDERERS: dict[int, Renderer] = {}


def get_renderer(samples: int = DEFAULT_SAMPLES) -> Renderer:
    """The process-wide renderer (one GL context, created on first use)."""
    if samples not in _RENDERERS:
        _RENDERERS[samples] = Renderer(samples)
    return _RENDERERS[samples]


def render_views(
    mesh: TexturedMesh,
    cameras: Cameras,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    samples: int = DEFAULT_SAMPLES,
) -> RenderResult:
    """Render ``mesh`` from every camera (see the module docstring for the output contract)."""
    return get_renderer(samples).render(mesh, cameras, background)
