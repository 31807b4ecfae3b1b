"""Visual meshes of a robot, one merged and decimated triangle mesh per URDF link in that link's frame (metres),
with per-vertex normals and a base colour; cached on disk as .npz so that generator workers load them fast."""

from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import fast_simplification
import numpy as np
import trimesh

from holo_pose_ros.robots.description import resolve_mesh_filename, urdf_file
from holo_pose_ros.robots.kinematics import RobotModel

CACHE_FORMAT = 2  # bump when the processing below changes, to invalidate old cache files
DEFAULT_COLOR = (0.8, 0.8, 0.8)  # light grey, for links whose URDF and meshes give no colour
MIN_LINK_FACES = 100  # no link is decimated below this many triangles
CREASE_ANGLE = np.radians(35.0)  # edges sharper than this keep separate normals on each side (radians)

_Part = tuple[trimesh.Trimesh, np.ndarray | None]  # a mesh and its RGB colour in [0, 1], when known


@dataclass(frozen=True)
class LinkMesh:
    """One link's visual geometry in the link frame: vertices (V,3) metres, unit normals (V,3), faces (F,3) and
    the base colour (3,) RGB in [0, 1]."""

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    color: np.ndarray


@dataclass
class _RawLink:
    """A link's merged, undecimated geometry and the area of each candidate colour (for the main colour)."""

    vertices: np.ndarray
    faces: np.ndarray
    color_areas: dict[tuple[float, float, float], float]


def load_link_meshes(model: RobotModel, max_faces: int = 12000) -> dict[str, LinkMesh]:
    """Every link with visuals -> its LinkMesh (URDF link order), the whole robot decimated to about `max_faces`
    triangles; read from the disk cache when the URDF has not changed since it was written."""
    path = _cache_path(model, max_faces)
    if path.is_file():
        return _read_cache(path)
    named_colors = {m.name: m.color.rgba for m in model.urdf.robot.materials if m.color is not None}
    links = [link for link in model.urdf.robot.links if link.visuals]
    raw = {link.name: _raw_link(link, model.urdf_dir, named_colors) for link in links}
    budgets = _face_budgets({name: len(r.faces) for name, r in raw.items()}, max_faces)
    meshes = {name: _finish_link(r, budgets[name]) for name, r in raw.items()}
    _write_cache(path, meshes)
    return meshes


# -- loading -------------------------------------------------------------------------------------------------
def _raw_link(link, urdf_dir: Path | None, named_colors: dict) -> _RawLink:
    """All visuals of one URDF link merged into one mesh in the link frame, duplicate vertices welded;
    `named_colors` are the URDF's top-level materials (name -> RGBA)."""
    parts, color_areas = [], {}
    for visual in link.visuals:
        for mesh, color in _visual_parts(visual, urdf_dir, named_colors):
            if visual.origin is not None:
                mesh.apply_transform(visual.origin)
            parts.append(mesh)
            if color is not None:
                key = tuple(float(c) for c in color[:3])
                color_areas[key] = color_areas.get(key, 0.0) + float(mesh.area)
    merged = trimesh.util.concatenate(parts)
    welded = trimesh.Trimesh(merged.vertices, merged.faces, process=True)  # weld by position, drop degenerate
    return _RawLink(np.asarray(welded.vertices), np.asarray(welded.faces), color_areas)


def _visual_parts(visual, urdf_dir: Path | None, named_colors: dict) -> list[_Part]:
    """One URDF visual as (mesh in the visual frame, RGB or None) pieces; the URDF material colour overrides the
    colours stored in the mesh file."""
    material = visual.material
    urdf_color = None
    if material is not None:
        urdf_color = material.color.rgba if material.color is not None else named_colors.get(material.name)
    geometry = visual.geometry
    if geometry.mesh is not None:
        parts = _mesh_file_parts(resolve_mesh_filename(geometry.mesh.filename, urdf_dir), geometry.mesh.scale)
    else:
        parts = [(_primitive(geometry), None)]
    if urdf_color is not None:
        parts = [(mesh, np.asarray(urdf_color)) for mesh, _ in parts]
    return parts


def _mesh_file_parts(filename: str, scale) -> list[_Part]:
    """The geometries of a mesh file (.dae/.obj/.stl) placed by the file's scene graph and scaled by the URDF
    scale, each with its material's main colour (RGB in [0, 1]) when the file has one."""
    scene = trimesh.load(filename, force="scene", process=False)
    scale_matrix = np.diag([*np.broadcast_to(np.asarray(1.0 if scale is None else scale, float), 3), 1.0])
    parts = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        mesh = trimesh.Trimesh(geom.vertices, geom.faces, process=False)
        mesh.apply_transform(scale_matrix @ transform)
        parts.append((mesh, _file_color(geom)))
    return parts


def _file_color(geom: trimesh.Trimesh) -> np.ndarray | None:
    """The main colour (RGB in [0, 1]) a mesh file gives a geometry, or None when it gives none."""
    visual = geom.visual
    if visual.kind == "texture" and getattr(visual, "material", None) is not None:
        return np.asarray(visual.material.main_color[:3], float) / 255.0
    if visual.kind in ("face", "vertex"):
        return np.asarray(visual.main_color[:3], float) / 255.0
    return None


def _primitive(geometry) -> trimesh.Trimesh:
    """A URDF box / cylinder (along z) / sphere, centred on the visual frame, metres."""
    if geometry.box is not None:
        return trimesh.creation.box(extents=geometry.box.size)
    if geometry.cylinder is not None:
        cylinder = geometry.cylinder
        return trimesh.creation.cylinder(radius=cylinder.radius, height=cylinder.length, sections=24)
    if geometry.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=2, radius=geometry.sphere.radius)
    raise ValueError("URDF visual without mesh, box, cylinder or sphere geometry")


# -- decimation and normals ----------------------------------------------------------------------------------
def _face_budgets(face_counts: dict[str, int], max_faces: int) -> dict[str, int]:
    """Triangles allowed per link: `max_faces` split in proportion to the links' own counts, at least
    MIN_LINK_FACES (or the link's count when smaller), never more than the link has."""
    total = sum(face_counts.values())
    return {name: min(n, max(MIN_LINK_FACES, round(max_faces * n / total))) for name, n in face_counts.items()}


def _finish_link(raw: _RawLink, target_faces: int) -> LinkMesh:
    """Decimate one link to `target_faces` triangles, compute crease-aware normals and pick its colour."""
    vertices, faces = _decimate(raw.vertices, raw.faces, target_faces)
    vertices, normals, faces = crease_normals(vertices, faces, CREASE_ANGLE)
    color = max(raw.color_areas, key=raw.color_areas.get) if raw.color_areas else DEFAULT_COLOR
    return LinkMesh(vertices.astype(np.float32), normals.astype(np.float32), faces.astype(np.int32),
                    np.asarray(color, np.float32))


def _decimate(vertices: np.ndarray, faces: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge-collapse decimation towards `target_faces` triangles. Open borders are kept: CAD exports
    (Baxter's especially) are patchworks of open shells, and collapsing their borders tears holes and spikes, so
    such links stay above their target."""
    if len(faces) > target_faces:
        vertices, faces = fast_simplification.simplify(vertices, faces, target_count=target_faces,
                                                       preserve_border=True)
    return np.asarray(vertices, float), np.asarray(faces, np.int64)


def crease_normals(vertices: np.ndarray, faces: np.ndarray,
                   crease: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex normals that are smooth across edges flatter than `crease` (radians) and sharp across the
    others: each face corner averages (area-weighted) the normals of the faces around its vertex that are within
    `crease` of its own face, then corners with the same vertex and normal share one output vertex."""
    weighted = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    unit = weighted / np.maximum(np.linalg.norm(weighted, axis=1, keepdims=True), 1e-20)
    corner_vertex = faces.ravel()
    corner_face = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(corner_vertex, kind="stable")
    sorted_vertex = corner_vertex[order]
    group_start = np.searchsorted(sorted_vertex, sorted_vertex, side="left")
    group_size = np.searchsorted(sorted_vertex, sorted_vertex, side="right") - group_start
    # every ordered pair (a, b) of corners that share a vertex, as positions in `order`
    a = np.repeat(np.arange(len(order)), group_size)
    offset_in_group = np.arange(len(a)) - np.repeat(np.cumsum(group_size) - group_size, group_size)
    b = np.repeat(group_start, group_size) + offset_in_group
    fa, fb = corner_face[order[a]], corner_face[order[b]]
    keep = np.einsum("ij,ij->i", unit[fa], unit[fb]) > np.cos(crease)
    corner_normal = np.zeros((len(order), 3))
    np.add.at(corner_normal, order[a[keep]], weighted[fb[keep]])
    corner_normal /= np.maximum(np.linalg.norm(corner_normal, axis=1, keepdims=True), 1e-20)
    key = np.column_stack([corner_vertex, np.round(corner_normal * 100).astype(np.int64)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return vertices[corner_vertex[first]], corner_normal[first], inverse.reshape(-1, 3)


# -- disk cache ----------------------------------------------------------------------------------------------
def _cache_path(model: RobotModel, max_faces: int) -> Path:
    """The cache file for this URDF (path and modification time, or its text) and face budget."""
    urdf = urdf_file(model.spec.urdf)
    source = model.spec.urdf.string if urdf is None else f"{urdf.resolve()}|{urdf.stat().st_mtime_ns}"
    digest = hashlib.sha1(f"{source}|{max_faces}|{CACHE_FORMAT}".encode()).hexdigest()[:16]
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "holo_pose_ros" / "meshes" / f"{model.name}_{digest}.npz"


def _write_cache(path: Path, meshes: dict[str, LinkMesh]) -> None:
    """Write the meshes atomically (temporary file + rename), so concurrent builders never leave a torn file; an
    unwritable cache only costs a warning."""
    values = list(meshes.values())
    arrays = dict(
        names=np.array(list(meshes)),
        vertices=np.concatenate([m.vertices for m in values]),
        normals=np.concatenate([m.normals for m in values]),
        faces=np.concatenate([m.faces for m in values]),
        colors=np.stack([m.color for m in values]),
        vertex_counts=np.array([len(m.vertices) for m in values]),
        face_counts=np.array([len(m.faces) for m in values]),
    )
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as e:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        warnings.warn(f"mesh cache {path} not written ({e}); the meshes will be rebuilt next time")


def _read_cache(path: Path) -> dict[str, LinkMesh]:
    """The meshes stored by _write_cache."""
    with np.load(path) as data:
        v_split = np.cumsum(data["vertex_counts"])[:-1]
        f_split = np.cumsum(data["face_counts"])[:-1]
        parts = zip(np.split(data["vertices"], v_split), np.split(data["normals"], v_split),
                    np.split(data["faces"], f_split), data["colors"])
        return {str(name): LinkMesh(v, n, f, c) for name, (v, n, f, c) in zip(data["names"], parts)}
