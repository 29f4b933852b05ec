"""Headless OpenGL renderer: RGB (uint8), depth (metres) and instance ids in one pass.

moderngl on EGL: Mesa's CPU rasteriser (llvmpipe) here, the GPU driver where there is one. Every part
of a scene is an oriented box drawn by instancing one unit cube; materials are procedural (stripes,
checker, wood grain, tiles, speckle) in the fragment shader. Many views are rendered into tiles of one
framebuffer and read back together, which is what makes CPU rendering fast enough for whole datasets.

Camera conventions are AI2-THOR's: rotation 0 looks along +z, 90 along +x, a positive horizon looks
down; 90 degree field of view, square images; depth is the distance along the viewing axis.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ..constants import CAMERA_HEIGHT, FIELD_OF_VIEW


class RendererUnavailable(RuntimeError):
    """No OpenGL context could be created (missing EGL / Mesa libraries)."""


VERTEX = """
#version 330
in vec3 in_pos;
in vec3 in_norm;
in vec3 i_center;
in vec3 i_size;
in float i_yaw;
in vec3 i_color;
in vec3 i_color2;
in float i_pattern;
in float i_scale;
in float i_inst;
uniform mat4 u_viewproj;
uniform mat4 u_view;
out vec3 v_world;
out vec3 v_local;
out vec3 v_norm;
out vec3 v_lnorm;
out float v_viewz;
flat out vec3 v_color;
flat out vec3 v_color2;
flat out int v_pattern;
flat out float v_scale;
flat out int v_inst;
void main() {
    float c = cos(radians(i_yaw));
    float s = sin(radians(i_yaw));
    vec3 lp = in_pos * i_size;
    // yaw turns local +z towards +x (AI2-THOR rotation)
    vec3 wp = vec3(c * lp.x + s * lp.z, lp.y, -s * lp.x + c * lp.z) + i_center;
    vec3 wn = vec3(c * in_norm.x + s * in_norm.z, in_norm.y, -s * in_norm.x + c * in_norm.z);
    v_world = wp;
    v_local = lp + i_center * 0.37;
    v_norm = wn;
    v_lnorm = in_norm;
    v_viewz = -(u_view * vec4(wp, 1.0)).z;
    v_color = i_color;
    v_color2 = i_color2;
    v_pattern = int(i_pattern + 0.5);
    v_scale = i_scale;
    v_inst = int(i_inst + 0.5);
    gl_Position = u_viewproj * vec4(wp, 1.0);
}
"""

FRAGMENT = """
#version 330
in vec3 v_world;
in vec3 v_local;
in vec3 v_norm;
in vec3 v_lnorm;
in float v_viewz;
flat in vec3 v_color;
flat in vec3 v_color2;
flat in int v_pattern;
flat in float v_scale;
flat in int v_inst;
uniform vec3 u_light;
uniform float u_ambient;
uniform float u_diffuse;
uniform vec3 u_tint;
uniform vec3 u_eye;
layout(location = 0) out vec4 out_color;
layout(location = 1) out float out_depth;
layout(location = 2) out int out_id;
float hash(vec2 p) { return fract(sin(dot(p, vec2(127.1, 311.7))) * 43758.5453); }
void main() {
    vec3 an = abs(v_lnorm);
    vec2 uv = an.x > 0.5 ? v_local.zy : (an.y > 0.5 ? v_local.xz : v_local.xy);
    vec2 q = uv / max(v_scale, 1e-3);
    float t = 0.0;
    if (v_pattern == 1) t = step(0.5, fract(q.x + 0.3 * q.y));
    else if (v_pattern == 2) t = mod(floor(q.x) + floor(q.y), 2.0);
    else if (v_pattern == 3) t = 0.5 + 0.5 * sin(q.x * 1.7 + 2.5 * sin(q.y * 0.35) + 0.8 * sin(q.x * 0.23));
    else if (v_pattern == 4) { vec2 f = fract(q); t = float(min(f.x, f.y) < 0.05); }
    else if (v_pattern == 5) t = hash(floor(q)) * 0.8;
    vec3 albedo = mix(v_color, v_color2, t);
    vec3 n = normalize(v_norm);
    vec3 l = normalize(-u_light);
    float diff = max(dot(n, l), 0.0) + 0.35 * max(dot(n, -l), 0.0);
    vec3 toeye = normalize(u_eye - v_world);
    float head = 0.15 * abs(dot(n, toeye));
    vec3 col = albedo * (u_ambient + u_diffuse * diff + head) * u_tint;
    out_color = vec4(clamp(col, 0.0, 1.0), 1.0);
    out_depth = v_viewz;
    out_id = v_inst;
}
"""


def _cube():
    faces = [
        ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
        ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
        ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
        ((0, -1, 0), (0, 0, -1), (1, 0, 0)),
        ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
        ((0, 0, -1), (-1, 0, 0), (0, 1, 0)),
    ]
    verts = []
    for n, u, v in faces:
        n, u, v = map(np.array, (n, u, v))
        c = n * 0.5
        quad = [c - u / 2 - v / 2, c + u / 2 - v / 2, c + u / 2 + v / 2, c - u / 2 + v / 2]
        for i in (0, 1, 2, 0, 2, 3):
            verts.append([*quad[i], *n])
    return np.array(verts, dtype="f4")


def camera_matrices(
    x: float,
    z: float,
    rotation: float,
    horizon: float,
    height: float = CAMERA_HEIGHT,
    fov: float = FIELD_OF_VIEW,
    near: float = 0.05,
    far: float = 30.0,
):
    """``(view, viewproj)`` 4x4 float32 (column-vector convention) for an AI2-THOR camera pose."""
    yaw, pitch = math.radians(rotation), math.radians(horizon)
    fwd = np.array([math.sin(yaw) * math.cos(pitch), -math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
    right = np.array([math.cos(yaw), 0.0, -math.sin(yaw)])  # +x when looking along +z (Unity's left-handed frame)
    up = np.cross(fwd, right)  # left-handed: up = fwd x right
    eye = np.array([x, height, z])
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -fwd
    view[:3, 3] = -view[:3, :3] @ eye
    f = 1.0 / math.tan(math.radians(fov) / 2)
    proj = np.zeros((4, 4))
    proj[0, 0], proj[1, 1] = f, f
    proj[2, 2], proj[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    proj[3, 2] = -1.0
    return view.astype("f4"), (proj @ view).astype("f4")


class Renderer:
    """Renders views of one scene at a time. ``size``: image side in pixels; ``tiles``: views per batch."""

    def __init__(self, size: int = 128, tiles: int = 16):
        try:
            import moderngl
        except ImportError as e:  # pragma: no cover - moderngl is a dependency
            raise RendererUnavailable(f"moderngl is not installed ({e})") from None
        try:
            # TSNAV_EGL_LIBRARY / TSNAV_GL_LIBRARY pick other library files (e.g. a vendor's EGL).
            self.ctx = moderngl.create_context(
                standalone=True,
                backend="egl",
                libgl=os.environ.get("TSNAV_GL_LIBRARY", "libGL.so.1"),
                libegl=os.environ.get("TSNAV_EGL_LIBRARY", "libEGL.so.1"),
            )
        except Exception as e:
            raise RendererUnavailable(
                f"cannot create a headless OpenGL context via EGL ({str(e).splitlines()[0] if str(e) else type(e).__name__}); "
                "install the Debian packages libegl1 libegl-mesa0 libgl1-mesa-dri libgl1"
            ) from None
        self.size = int(size)
        self.cols = int(math.ceil(math.sqrt(tiles)))
        self.rows = int(math.ceil(tiles / self.cols))
        self.tiles = self.cols * self.rows
        W, H = self.cols * self.size, self.rows * self.size
        ctx = self.ctx
        self.color = ctx.renderbuffer((W, H), components=4)
        self.depthv = ctx.renderbuffer((W, H), components=1, dtype="f4")
        self.ids = ctx.renderbuffer((W, H), components=1, dtype="i4")
        self.zbuf = ctx.depth_renderbuffer((W, H))
        self.fbo = ctx.framebuffer(color_attachments=[self.color, self.depthv, self.ids], depth_attachment=self.zbuf)
        self.prog = ctx.program(vertex_shader=VERTEX, fragment_shader=FRAGMENT)
        self.cube = ctx.buffer(_cube().tobytes())
        self.inst_buf = None
        self.vao = None
        self.n_inst = 0

    def set_scene(self, parts: np.ndarray, light: dict | None = None) -> None:
        """``parts``: (N, 16) float rows of ``scene.json`` (centre, size, yaw, colours, pattern, scale, inst)."""
        parts = np.ascontiguousarray(np.asarray(parts, dtype="f4"))
        if parts.ndim != 2 or parts.shape[1] != 16:
            raise ValueError(f"parts must be an (N, 16) array, got shape {parts.shape}")
        if self.inst_buf is not None:
            self.inst_buf.release()
            self.vao.release()
        self.inst_buf = self.ctx.buffer(parts.tobytes())
        self.vao = self.ctx.vertex_array(
            self.prog,
            [
                (self.cube, "3f 3f", "in_pos", "in_norm"),
                (
                    self.inst_buf,
                    "3f 3f 1f 3f 3f 1f 1f 1f/i",
                    "i_center",
                    "i_size",
                    "i_yaw",
                    "i_color",
                    "i_color2",
                    "i_pattern",
                    "i_scale",
                    "i_inst",
                ),
            ],
        )
        self.n_inst = len(parts)
        light = light or {}
        self.prog["u_light"].value = tuple(light.get("direction", (0.3, -2.5, 0.2)))
        self.prog["u_ambient"].value = float(light.get("ambient", 0.5))
        self.prog["u_diffuse"].value = float(light.get("diffuse", 0.45))
        self.prog["u_tint"].value = tuple(light.get("tint", (1.0, 1.0, 1.0)))

    def render(self, poses: np.ndarray, height: float = CAMERA_HEIGHT):
        """Render ``poses`` (V, 4) rows of (x, z, rotation, horizon) from a camera ``height`` m above the floor.

        Returns ``rgb`` (V, S, S, 3) uint8, ``depth`` (V, S, S) float32 metres, ``ids`` (V, S, S) int32,
        image row 0 at the top.
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        V, S = len(poses), self.size
        rgb = np.empty((V, S, S, 3), np.uint8)
        depth = np.empty((V, S, S), np.float32)
        ids = np.empty((V, S, S), np.int32)
        for start in range(0, V, self.tiles):
            chunk = poses[start : start + self.tiles]
            n = len(chunk)
            self.fbo.use()
            self.ctx.enable(self.ctx.DEPTH_TEST)
            self.fbo.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
            # Integer and float attachments are cleared explicitly (clear() only sets colour 0 reliably).
            self.fbo.clear(color=(0, 0, 0, 0), viewport=None)
            for i, (x, z, r, h) in enumerate(chunk):
                col, row = i % self.cols, i // self.cols
                self.fbo.viewport = (col * S, row * S, S, S)
                view, vp = camera_matrices(x, z, r, h, height=height)
                self.prog["u_viewproj"].write(vp.T.tobytes())
                self.prog["u_view"].write(view.T.tobytes())
                self.prog["u_eye"].value = (float(x), float(height), float(z))
                self.vao.render(instances=self.n_inst)
            W = self.cols * S
            c = np.frombuffer(self.fbo.read(components=3, attachment=0), np.uint8).reshape(self.rows * S, W, 3)
            d = np.frombuffer(self.fbo.read(components=1, attachment=1, dtype="f4"), np.float32).reshape(
                self.rows * S, W
            )
            m = np.frombuffer(self.fbo.read(components=1, attachment=2, dtype="i4"), np.int32).reshape(self.rows * S, W)
            for k, arr, out in ((0, c, rgb), (1, d, depth), (2, m, ids)):
                # tiles -> (rows, S, cols, S, ...) -> (rows*cols, S, S, ...); GL rows start at the bottom.
                t = arr.reshape(self.rows, S, self.cols, S, *arr.shape[2:]).swapaxes(1, 2)
                t = t.reshape(self.rows * self.cols, S, S, *arr.shape[2:])[:n, ::-1]
                out[start : start + n] = t
        return rgb, depth, ids

    def release(self) -> None:
        self.ctx.release()
