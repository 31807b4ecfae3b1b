"""Offscreen rendering of a posed robot (plus distractor primitives) through an OpenCV pinhole camera with
moderngl/EGL: one pass writes an RGBA image and a per-link label image (two colour attachments), and the depth
buffer is read back as metric depth. Camera frame: x right, y down, z forward, metres."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import moderngl
import numpy as np
import trimesh

from holo_pose_ros.data.meshes import CREASE_ANGLE, LinkMesh, crease_normals

PATTERNS = ("plain", "stripes", "checker", "noise")
SHADINGS = ("phong", "flat", "toon")  # fragment shader modes, see Shading
PRIMITIVE_KINDS = ("box", "sphere", "cylinder")
DISTRACTOR_LABEL = 255  # label of distractor pixels; robot links get 1..254, nothing 0

def robot_foreground(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool robot pixels of a label mask (1 + link index on the robot, 0 nothing, DISTRACTOR_LABEL
    distractors): what a foreground mask is trained towards and a silhouette is fitted to."""
    return (labels > 0) & (labels != DISTRACTOR_LABEL)


_VERTEX_SHADER = """
#version 330
uniform mat4 u_proj;   // camera -> clip, from K
uniform mat4 u_model;  // object -> camera (rigid)
uniform vec3 u_scale;  // per-axis object scale (primitives), metres per mesh unit
in vec3 in_position;
in vec3 in_normal;
out vec3 v_obj;        // object-space position, metres (drives the procedural patterns)
out vec3 v_cam;        // camera-space position, metres
out vec3 v_normal;     // camera-space normal (unnormalised)
void main() {
    v_obj = in_position * u_scale;
    vec4 cam = u_model * vec4(v_obj, 1.0);
    v_cam = cam.xyz;
    v_normal = mat3(u_model) * (in_normal / u_scale);
    gl_Position = u_proj * cam;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 u_color;
uniform vec3 u_color2;
uniform int u_pattern;          // index into PATTERNS
uniform float u_pattern_scale;  // metres per period
uniform float u_specular;
uniform float u_shininess;
uniform vec3 u_light_dir;       // camera frame, from the light toward the scene
uniform vec3 u_light_color;
uniform vec3 u_ambient;
uniform uint u_label;
uniform int u_shading;          // index into SHADINGS
uniform float u_bands;          // toon: number of diffuse levels
in vec3 v_obj;
in vec3 v_cam;
in vec3 v_normal;
layout(location = 0) out vec4 f_color;
layout(location = 1) out uint f_label;

float hash(vec3 p) {
    p = fract(p * vec3(0.1031, 0.1030, 0.0973));
    p += dot(p, p.yxz + 33.33);
    return fract((p.x + p.y) * p.z);
}

float value_noise(vec3 p) {
    vec3 i = floor(p);
    vec3 f = smoothstep(0.0, 1.0, fract(p));
    return mix(mix(mix(hash(i), hash(i + vec3(1, 0, 0)), f.x),
                   mix(hash(i + vec3(0, 1, 0)), hash(i + vec3(1, 1, 0)), f.x), f.y),
               mix(mix(hash(i + vec3(0, 0, 1)), hash(i + vec3(1, 0, 1)), f.x),
                   mix(hash(i + vec3(0, 1, 1)), hash(i + vec3(1, 1, 1)), f.x), f.y), f.z);
}

float pattern_weight(vec3 p) {
    vec3 q = p / u_pattern_scale + 0.25;  // quarter-period offset keeps cell edges off faces at round sizes
    if (u_pattern == 1) return step(0.5, fract(q.z));
    if (u_pattern == 2) return mod(floor(q.x) + floor(q.y) + floor(q.z), 2.0);
    if (u_pattern == 3) return 0.65 * value_noise(q) + 0.35 * value_noise(2.7 * q);
    return 0.0;
}

void main() {
    vec3 albedo = pow(mix(u_color, u_color2, pattern_weight(v_obj)), vec3(2.2));
    vec3 n = normalize(v_normal);
    if (u_shading == 1) n = normalize(cross(dFdx(v_cam), dFdy(v_cam)));  // flat: the facet's own normal
    vec3 v = normalize(-v_cam);
    if (dot(n, v) < 0.0) n = -n;  // two-sided lighting: meshes may be open or inconsistently wound
    vec3 l = -normalize(u_light_dir);
    float diffuse = max(dot(n, l), 0.0);
    float spec = diffuse > 0.0 ? u_specular * pow(max(dot(n, normalize(l + v)), 0.0), u_shininess) : 0.0;
    if (u_shading == 2) {  // toon: u_bands diffuse levels 0 .. 1 and a hard-edged highlight
        diffuse = min(floor(diffuse * u_bands), u_bands - 1.0) / (u_bands - 1.0);
        spec = spec > 0.5 * u_specular ? u_specular : 0.0;
    }
    vec3 linear = albedo * (u_ambient + u_light_color * diffuse) + u_light_color * spec;
    f_color = vec4(pow(clamp(linear, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
    f_label = u_label;
}
"""


@dataclass(frozen=True)
class Material:
    """Surface look: base colour and second pattern colour (sRGB in [0, 1]), a procedural pattern computed from the
    object-space position with period `pattern_scale` (metres), and Blinn-Phong specular strength (0..1) and
    exponent."""

    color: tuple[float, float, float] | np.ndarray = (0.8, 0.8, 0.8)
    color2: tuple[float, float, float] | np.ndarray = (0.2, 0.2, 0.2)
    pattern: str = "plain"
    pattern_scale: float = 0.05
    specular: float = 0.3
    shininess: float = 32.0

    def __post_init__(self):
        if self.pattern not in PATTERNS:
            raise ValueError(f"unknown pattern '{self.pattern}', expected one of {PATTERNS}")


@dataclass(frozen=True)
class Light:
    """A directional light: `direction_cam` the unit direction (camera frame) from the light toward the scene,
    its colour and the ambient colour (linear RGB)."""

    direction_cam: tuple[float, float, float] | np.ndarray = (0.3, 0.6, 1.0)
    color: tuple[float, float, float] | np.ndarray = (0.9, 0.9, 0.9)
    ambient: tuple[float, float, float] | np.ndarray = (0.25, 0.25, 0.25)


@dataclass(frozen=True)
class Shading:
    """How surfaces are lit, for the whole frame: `phong` (smooth Blinn-Phong, the training looks), `flat` (one
    normal per facet, from screen-space derivatives of the camera position) or `toon` (Blinn-Phong with the
    diffuse term quantized to `bands` levels, 2 or more, and a hard-edged highlight)."""

    mode: str = "phong"
    bands: int = 3

    def __post_init__(self):
        if self.mode not in SHADINGS:
            raise ValueError(f"unknown shading '{self.mode}', expected one of {SHADINGS}")
        if self.bands < 2:
            raise ValueError(f"toon shading needs at least 2 bands, got {self.bands}")


@dataclass(frozen=True)
class Primitive:
    """A distractor object: a box (size = full extents), sphere (radius size[0]) or z-axis cylinder (radius
    size[0], height size[1]), centred on its frame, posed by T_cam<-obj (4, 4); metres."""

    kind: str
    size: tuple[float, float, float] | np.ndarray
    T_cam_obj: np.ndarray
    material: Material = Material()

    def __post_init__(self):
        if self.kind not in PRIMITIVE_KINDS:
            raise ValueError(f"unknown primitive '{self.kind}', expected one of {PRIMITIVE_KINDS}")

    @property
    def scale(self) -> np.ndarray:
        """Per-axis scale (metres) applied to the unit primitive mesh."""
        s = np.asarray(self.size, np.float32)
        if self.kind == "box":
            return s[:3]
        if self.kind == "sphere":
            return np.full(3, s[0], np.float32)
        return np.array([s[0], s[0], s[1]], np.float32)


@dataclass
class RenderResult:
    """rgba (H, W, 4) uint8 with alpha 0 where nothing was drawn; labels (H, W) uint8: 0 nothing, 1 + link index
    (order of the `meshes` keys) on robot pixels, DISTRACTOR_LABEL on distractors; depth (H, W) float32 metres
    along the camera z axis, 0 where nothing was drawn. Row 0 is the top of the image."""

    rgba: np.ndarray
    labels: np.ndarray
    depth: np.ndarray


def projection_from_K(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """GL clip matrix (4, 4) for an OpenCV camera K: camera point P lands exactly on pixel K P / z (pixel (0, 0)
    is the centre of the top-left pixel). NDC y grows with the image row, so GL's bottom-up readback already
    yields top-to-bottom rows."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([
        [2 * fx / width, K[0, 1] * 2 / width, 2 * (cx + 0.5) / width - 1, 0],
        [0, 2 * fy / height, 2 * (cy + 0.5) / height - 1, 0],
        [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, 1, 0],
    ], dtype=np.float64)


@lru_cache(maxsize=None)
def unit_primitive(kind: str) -> LinkMesh:
    """Unit box (extents 1), sphere (radius 1) or z-axis cylinder (radius 1, height 1), centred, with normals."""
    mesh = {
        "box": lambda: trimesh.creation.box(extents=(1.0, 1.0, 1.0)),
        "sphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=1.0),
        "cylinder": lambda: trimesh.creation.cylinder(radius=1.0, height=1.0, sections=32),
    }[kind]()
    vertices, normals, faces = crease_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces), CREASE_ANGLE)
    return LinkMesh(vertices.astype(np.float32), normals.astype(np.float32), faces.astype(np.int32),
                    np.full(3, 0.8, np.float32))


class _GlState:
    """The GL context of one process with its program, framebuffer and the meshes uploaded so far."""

    def __init__(self, width: int, height: int):
        self.ctx = moderngl.create_context(standalone=True, backend="egl", require=330)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        members = {name: self.program[name] for name in self.program}
        self.uniforms = {name: m for name, m in members.items() if isinstance(m, moderngl.Uniform)}
        size = (width, height)
        self.fbo = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer(size, 4, dtype="f1"),   # RGBA8
                               self.ctx.renderbuffer(size, 1, dtype="u1")],  # R8UI labels
            depth_attachment=self.ctx.depth_renderbuffer(size),
        )
        self.vaos: dict[int, tuple[LinkMesh, moderngl.VertexArray]] = {}

    def vao(self, mesh: LinkMesh) -> moderngl.VertexArray:
        """The vertex array of `mesh`, uploaded on first use (keyed by identity; the mesh is kept alive)."""
        entry = self.vaos.get(id(mesh))
        if entry is None:
            interleaved = np.hstack([mesh.vertices, mesh.normals]).astype("f4")
            vbo = self.ctx.buffer(interleaved.tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(mesh.faces, dtype="i4").tobytes())
            vao = self.ctx.vertex_array(self.program, [(vbo, "3f 3f", "in_position", "in_normal")],
                                        index_buffer=ibo, index_element_size=4)
            entry = self.vaos[id(mesh)] = (mesh, vao)
        return entry[1]


class Renderer:
    """Renders RGBA, labels and metric depth at a fixed image size (pixels). The GL context is created lazily in
    the process that first renders (and again after a fork), so a Renderer can be built or pickled before
    handing it to worker processes. Depth range `near`..`far` in metres."""

    def __init__(self, width: int, height: int, near: float = 0.05, far: float = 20.0):
        self.width, self.height, self.near, self.far = int(width), int(height), float(near), float(far)
        self._gl: _GlState | None = None
        self._pid: int | None = None

    def __getstate__(self) -> dict:
        return {"width": self.width, "height": self.height, "near": self.near, "far": self.far}

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state)

    def _state(self) -> _GlState:
        """This process's GL state, created on first use (a context inherited through fork is not usable)."""
        if self._gl is None or self._pid != os.getpid():
            self._gl, self._pid = _GlState(self.width, self.height), os.getpid()
        return self._gl

    def release(self) -> None:
        """Free the GL context and uploaded meshes (a later render creates them again)."""
        if self._gl is not None and self._pid == os.getpid():
            self._gl.ctx.release()
        self._gl = None

    def render(self, link_poses: dict[str, np.ndarray], meshes: dict[str, LinkMesh], K: np.ndarray,
               materials: dict[str, Material], light: Light, distractors: Sequence[Primitive] = (),
               shading: Shading = Shading()) -> RenderResult:
        """Draw every link of `meshes` at its pose T_cam<-link (4, 4, metres) with `materials[link]` (default: the
        mesh colour, plain) and the distractors, through camera K (3, 3, pixels), all lit with `shading`. Meshes
        are uploaded once per LinkMesh object and kept: pass the same objects every frame rather than reloading
        them."""
        if len(meshes) >= DISTRACTOR_LABEL:
            raise ValueError(f"at most {DISTRACTOR_LABEL - 1} links can be labelled, got {len(meshes)}")
        gl = self._state()
        with gl.ctx:  # make this renderer's context current: a process may hold several
            gl.fbo.use()
            gl.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._set_camera(gl, np.asarray(K, float), light, shading)
            ones = np.ones(3, np.float32)
            for label, (name, mesh) in enumerate(meshes.items(), start=1):
                material = materials[name] if name in materials else Material(color=mesh.color)
                self._draw(gl, gl.vao(mesh), link_poses[name], ones, material, label)
            for prim in distractors:
                self._draw(gl, gl.vao(unit_primitive(prim.kind)), prim.T_cam_obj, prim.scale, prim.material,
                           DISTRACTOR_LABEL)
            return self._read(gl)

    def _set_camera(self, gl: _GlState, K: np.ndarray, light: Light, shading: Shading) -> None:
        """Per-frame uniforms: projection from K, the light and the shading mode."""
        u = gl.uniforms
        u["u_proj"].write(projection_from_K(K, self.width, self.height, self.near, self.far).T.astype("f4").tobytes())
        u["u_light_dir"].value = tuple(map(float, light.direction_cam))
        u["u_light_color"].value = tuple(map(float, light.color))
        u["u_ambient"].value = tuple(map(float, light.ambient))
        u["u_shading"].value = SHADINGS.index(shading.mode)
        u["u_bands"].value = float(shading.bands)

    @staticmethod
    def _draw(gl: _GlState, vao: moderngl.VertexArray, T_cam_obj: np.ndarray, scale: np.ndarray,
              material: Material, label: int) -> None:
        """One draw call: the object's pose (4, 4, metres), scale, material and label."""
        u = gl.uniforms
        u["u_model"].write(np.asarray(T_cam_obj, "f4").T.tobytes())
        u["u_scale"].write(np.asarray(scale, "f4").tobytes())
        u["u_color"].write(np.asarray(material.color, "f4").tobytes())
        u["u_color2"].write(np.asarray(material.color2, "f4").tobytes())
        u["u_pattern"].value = PATTERNS.index(material.pattern)
        u["u_pattern_scale"].value = float(material.pattern_scale)
        u["u_specular"].value = float(material.specular)
        u["u_shininess"].value = float(material.shininess)
        u["u_label"].value = int(label)
        vao.render(moderngl.TRIANGLES)

    def _read(self, gl: _GlState) -> RenderResult:
        """Read back the three images; window depth d in [0, 1] becomes z = near far / (far - d (far - near))."""
        h, w = self.height, self.width
        rgba = np.empty((h, w, 4), np.uint8)
        labels = np.empty((h, w), np.uint8)
        window_depth = np.empty((h, w), np.float32)
        gl.fbo.read_into(rgba, components=4, attachment=0)
        gl.fbo.read_into(labels, components=1, attachment=1, dtype="u1")
        gl.fbo.read_into(window_depth, components=1, attachment=-1, dtype="f4")
        empty = window_depth >= 1.0
        depth = (self.near * self.far) / (self.far - window_depth * (self.far - self.near))
        depth[empty] = 0.0
        labels[empty] = 0  # integer attachments are not reliably cleared by a float clear; depth is the truth
        return RenderResult(rgba, labels, depth.astype(np.float32, copy=False))
