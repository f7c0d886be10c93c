"""Headless CPU renderer of linear radiance (float32), moderngl on EGL (Mesa llvmpipe).

One directional sun casts shadows through a shadow map rendered once (the target and its lights are
fixed in the world frame, only the camera moves); fill lights and an ambient term are unshadowed.
The camera is an OpenCV pinhole: the vertex shader maps camera coordinates straight to clip space so
that pixel ``(u, v)`` of the returned image is exactly where ``K · X_c`` lands (pixel centres at integer
coordinates, row 0 at the top). Multisampling anti-aliases silhouettes so that edge pixels change
gradually as the target moves. With lens distortion (OpenCV ``k1 k2 p1 p2 k3``), a pinhole image large
enough to hold every distorted pixel's undistorted position is rendered and resampled (``cv2.remap``).
"""

from __future__ import annotations

import contextlib

import cv2
import moderngl
import numpy as np

from evgs.data.sequence import Camera
from evgs.geometry import invert_pose
from evgs.sim.lights import Lighting, unit
from evgs.sim.materials import material_table
from evgs.sim.scene import Scene

MAX_FILLS = 4


def _load_triton_before_mesa() -> None:
    """Mesa's llvmpipe loads its LLVM into the process; triton (imported lazily by torch, e.g. when an
    optimizer is built) carries its own LLVM and segfaults if it loads after Mesa's. Loaded first, both
    coexist — this keeps simulate-then-optimise in one process (``evgs run``, the tests) working."""
    with contextlib.suppress(ImportError):
        import triton  # noqa: F401


_VERTEX = """
#version 330
uniform mat4 world_to_cam;
uniform vec4 intr;      // fx, fy, cx, cy
uniform vec2 size;      // width, height
uniform vec2 near_far;
in vec3 in_pos;
in vec3 in_normal;
in int in_mat;
out vec3 v_pos;
out vec3 v_normal;
flat out int v_mat;
void main() {
    vec4 pc = world_to_cam * vec4(in_pos, 1.0);
    float z = pc.z;
    // Window x = u + 0.5 with u = fx X/Z + cx (OpenCV pixel centres at integers); NDC = 2 x / W - 1.
    float xc = 2.0 * (intr.x * pc.x + (intr.z + 0.5) * z) / size.x - z;
    float yc = 2.0 * (intr.y * pc.y + (intr.w + 0.5) * z) / size.y - z;
    float n = near_far.x, f = near_far.y;
    gl_Position = vec4(xc, yc, (f + n) / (f - n) * z - 2.0 * f * n / (f - n), z);
    v_pos = in_pos;
    v_normal = in_normal;
    v_mat = in_mat;
}
"""

_FRAGMENT = """
#version 330
uniform vec3 cam_pos;
uniform vec3 sun_dir;
uniform float sun;
uniform vec3 fill_dir[4];
uniform float fill[4];
uniform float ambient;
uniform mat4 sun_vp;
uniform float shadow_bias;
uniform sampler2DShadow shadow_map;
uniform vec4 mat_a[8];  // albedo, specular, shininess, bump
uniform vec4 mat_b[8];  // bump_freq, cell_pitch, -, -
in vec3 v_pos;
in vec3 v_normal;
flat in int v_mat;
out float radiance;

float hash(vec3 p) {
    p = fract(p * 0.3183099 + 0.1) * 17.0;
    return fract(p.x * p.y * p.z * (p.x + p.y + p.z));
}
vec3 hash3(vec3 c) { return vec3(hash(c), hash(c + 17.13), hash(c + 43.71)) - 0.5; }

// Lambert + normalised Blinn-Phong, times the cosine of incidence.
float lobe(vec3 n, vec3 l, vec3 v, float albedo, float ks, float shin) {
    float ndl = max(dot(n, l), 0.0);
    float spec = ks * (shin + 8.0) / 8.0 * pow(max(dot(n, normalize(l + v)), 0.0), shin);
    return ndl * (albedo + spec);
}

void main() {
    vec4 ma = mat_a[v_mat];
    vec4 mb = mat_b[v_mat];
    vec3 v = normalize(cam_pos - v_pos);
    vec3 ng = normalize(v_normal);
    if (dot(ng, v) < 0.0) ng = -ng;  // two-sided: thin panels are seen from both sides
    vec3 n = ng;
    if (ma.w > 0.0) {
        // Crinkled foil: a random facet tilt per 3-D cell, two octaves.
        n = normalize(n + ma.w * (hash3(floor(v_pos * mb.x)) + 0.5 * hash3(floor(v_pos * mb.x * 2.3 + 0.5))));
        if (dot(n, v) < 0.05) n = ng;
    }
    float albedo = ma.x;
    if (mb.y > 0.0) {
        vec3 q = fract(v_pos / mb.y);
        vec3 an = abs(ng);
        vec2 uv = an.x > max(an.y, an.z) ? q.yz : (an.y > an.z ? q.xz : q.xy);
        albedo = mix(albedo, 0.6, step(0.92, max(uv.x, uv.y)));
    }
    vec3 ns = dot(ng, sun_dir) >= 0.0 ? ng : -ng;
    vec4 ls = sun_vp * vec4(v_pos + ns * shadow_bias, 1.0);
    float lit = texture(shadow_map, ls.xyz * 0.5 + 0.5);
    float r = sun * lit * lobe(n, sun_dir, v, albedo, ma.y, ma.z) + ambient * albedo;
    for (int i = 0; i < 4; i++) r += fill[i] * lobe(n, fill_dir[i], v, albedo, ma.y, ma.z);
    radiance = r;
}
"""

_SHADOW_VERTEX = """
#version 330
uniform mat4 sun_vp;
in vec3 in_pos;
void main() { gl_Position = sun_vp * vec4(in_pos, 1.0); }
"""

_SHADOW_FRAGMENT = """
#version 330
void main() {}
"""


def _mat(m: np.ndarray) -> bytes:
    """Row-major numpy 4×4 → GLSL column-major bytes."""
    return np.ascontiguousarray(m.T, np.float32).tobytes()


def sun_view_projection(direction: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Orthographic world → clip matrix of the sun covering the sphere (centre, radius)."""
    f = -direction
    helper = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.cross(f, helper)
    a /= np.linalg.norm(a)
    b = np.cross(a, f)
    eye = centre + 2.0 * radius * direction
    m = np.eye(4)
    m[0, :3], m[0, 3] = a / radius, -a @ centre / radius
    m[1, :3], m[1, 3] = b / radius, -b @ centre / radius
    m[2, :3], m[2, 3] = f / (2 * radius), -f @ eye / (2 * radius) - 1.0
    return m


def distortion_map(camera: Camera) -> tuple[Camera, np.ndarray, np.ndarray]:
    """For a distorted camera: the pinhole camera to render (same focal lengths, a canvas covering every
    undistorted pixel position plus a margin) and the float32 ``remap`` tables from it."""
    w, h = camera.width, camera.height
    uv = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, np.asarray(camera.distortion, np.float64))
    x = und.reshape(h, w, 2)
    px = x[..., 0] * camera.fx + camera.cx
    py = x[..., 1] * camera.fy + camera.cy
    margin = 2
    x0, y0 = int(np.floor(px.min())) - margin, int(np.floor(py.min())) - margin
    x1, y1 = int(np.ceil(px.max())) + margin, int(np.ceil(py.max())) + margin
    pinhole = Camera(x1 - x0 + 1, y1 - y0 + 1, camera.fx, camera.fy, camera.cx - x0, camera.cy - y0)
    return pinhole, (px - x0).astype(np.float32), (py - y0).astype(np.float32)


class Renderer:
    """Render a static scene from any camera pose. Use as a context manager (releases the GL context)."""

    def __init__(
        self,
        scene: Scene,
        camera: Camera,
        lighting: Lighting,
        *,
        msaa: int = 4,
        shadow_size: int = 2048,
        near: float = 0.05,
        far: float = 500.0,
    ) -> None:
        self.camera = camera
        self.remap: tuple[np.ndarray, np.ndarray] | None = None
        if any(camera.distortion):
            camera, *maps = distortion_map(camera)
            self.remap = (maps[0], maps[1])
        self.canvas = camera
        _load_triton_before_mesa()
        self.ctx = moderngl.create_standalone_context(backend="egl")
        ctx = self.ctx
        samples = min(msaa, ctx.max_samples) if msaa > 1 else 0
        centre, radius = scene.bounds
        sun_vp = sun_view_projection(unit(lighting.sun_dir), centre, radius)

        pos = ctx.buffer(np.ascontiguousarray(scene.triangles, np.float32).tobytes())
        nrm = ctx.buffer(np.ascontiguousarray(scene.normals, np.float32).tobytes())
        mat = ctx.buffer(np.repeat(scene.material.astype(np.int32), 3).tobytes())

        shadow_prog = ctx.program(vertex_shader=_SHADOW_VERTEX, fragment_shader=_SHADOW_FRAGMENT)
        shadow_prog["sun_vp"].write(_mat(sun_vp))
        self.shadow_map = ctx.depth_texture((shadow_size, shadow_size))
        self.shadow_map.compare_func = "<="
        self.shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
        shadow_fbo = ctx.framebuffer(depth_attachment=self.shadow_map)
        shadow_fbo.use()
        shadow_fbo.clear(depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.vertex_array(shadow_prog, [(pos, "3f", "in_pos")]).render(moderngl.TRIANGLES)

        self.prog = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        p = self.prog
        p["intr"].value = (camera.fx, camera.fy, camera.cx, camera.cy)
        p["size"].value = (camera.width, camera.height)
        p["near_far"].value = (near, far)
        p["sun_vp"].write(_mat(sun_vp))
        p["sun_dir"].value = tuple(unit(lighting.sun_dir))
        p["sun"].value = lighting.sun
        fills = list(lighting.fills)[:MAX_FILLS]
        if len(lighting.fills) > MAX_FILLS:
            raise ValueError(f"at most {MAX_FILLS} fill lights are supported, got {len(lighting.fills)}")
        dirs = [tuple(unit(d)) for d, _ in fills] + [(0.0, 0.0, 1.0)] * (MAX_FILLS - len(fills))
        p["fill_dir"].value = dirs
        p["fill"].value = [i for _, i in fills] + [0.0] * (MAX_FILLS - len(fills))
        p["ambient"].value = lighting.ambient
        p["shadow_bias"].value = 3.0 * radius / shadow_size
        table = np.zeros((8, 8), np.float32)
        mt = material_table()
        table[: len(mt)] = mt
        p["mat_a"].write(np.ascontiguousarray(table[:, :4]).tobytes())
        p["mat_b"].write(np.ascontiguousarray(table[:, 4:]).tobytes())
        p["shadow_map"].value = 0
        self.vao = ctx.vertex_array(
            p, [(pos, "3f", "in_pos"), (nrm, "3f", "in_normal"), (mat, "1i", "in_mat")]
        )
        size = (camera.width, camera.height)
        self.fbo = ctx.framebuffer(
            [ctx.renderbuffer(size, components=1, dtype="f4", samples=samples)],
            ctx.depth_renderbuffer(size, samples=samples),
        )
        self.resolved = (
            ctx.framebuffer([ctx.renderbuffer(size, components=1, dtype="f4")]) if samples else self.fbo
        )
        self.near_far = (near, far)
        self.depth_fbo: moderngl.Framebuffer | None = None  # single-sampled, made on first depth()

    def _draw(self, T_wc: np.ndarray, fbo: moderngl.Framebuffer) -> None:
        T_cw = invert_pose(np.asarray(T_wc, np.float64))
        self.prog["world_to_cam"].write(_mat(T_cw))
        self.prog["cam_pos"].value = tuple(np.asarray(T_wc)[:3, 3])
        fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.shadow_map.use(location=0)
        self.vao.render(moderngl.TRIANGLES)

    def _undistort(self, img: np.ndarray, interpolation: int, border: float) -> np.ndarray:
        if self.remap is None:
            return img
        return cv2.remap(img, *self.remap, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=border)

    def render(self, T_wc: np.ndarray) -> np.ndarray:
        """Linear radiance (H, W) float32 seen from camera-to-world pose ``T_wc``."""
        self._draw(T_wc, self.fbo)
        if self.resolved is not self.fbo:
            self.ctx.copy_framebuffer(self.resolved, self.fbo)
        data = self.resolved.read(components=1, dtype="f4")
        img = np.frombuffer(data, np.float32).reshape(self.canvas.height, self.canvas.width)
        return self._undistort(img, cv2.INTER_LINEAR, 0.0)

    def depth(self, T_wc: np.ndarray) -> np.ndarray:
        """Camera-frame depth ``z`` (H, W) float32 of the nearest surface at each pixel centre seen from
        ``T_wc``; inf where the ray meets nothing (the ground truth of a map's depth, evgs.eval.depth).

        Single-sampled, so a silhouette pixel holds one surface's depth, not a blend of two."""
        w, h = self.canvas.width, self.canvas.height
        if self.depth_fbo is None:
            self.depth_fbo = self.ctx.framebuffer(
                [self.ctx.renderbuffer((w, h), components=1, dtype="f4")], self.ctx.depth_renderbuffer((w, h))
            )
        self._draw(T_wc, self.depth_fbo)
        window = np.frombuffer(
            self.depth_fbo.read(components=1, attachment=-1, dtype="f4"), np.float32
        ).reshape(h, w)
        n, f = self.near_far
        ndc = 2.0 * window.astype(np.float64) - 1.0  # inverts the vertex shader's projection of z
        with np.errstate(divide="ignore"):
            z = np.where(window < 1.0, 2.0 * f * n / ((f + n) - ndc * (f - n)), np.inf)
        return self._undistort(z.astype(np.float32), cv2.INTER_NEAREST, np.inf)

    def release(self) -> None:
        self.ctx.release()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
