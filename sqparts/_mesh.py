"""Meshes at the edge: tessellate parts (watertight), export scenes, ray-cast meshes.

Tessellation samples Eq. (1) on a latitude/longitude grid whose angles are spaced so the
samples are even both where the surface is flat and around its rounded edges (the union
of angles equally spaced in ``sin^ε`` and in ``cos^ε``), so box-like parts keep sharp
edges and round parts stay round.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, camera_rays
from ._compile import persistent_jit
from ._io import atomic_write
from ._part import Part, surface_point

if TYPE_CHECKING:
    import trimesh

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".off")


def _quarter_angles(e: float, n: int) -> np.ndarray:
    """Angles in [0, π/2] spaced evenly in both sin(θ)^e and cos(θ)^e."""
    s = np.linspace(0.0, 1.0, n)
    a = np.arcsin(np.clip(s ** (1.0 / e), 0, 1))
    b = np.arccos(np.clip(s ** (1.0 / e), 0, 1))
    c = np.linspace(0.0, np.pi / 2, n)
    angles = np.unique(np.round(np.concatenate([a, b, c]), 9))
    keep = np.concatenate([[True], np.diff(angles) > 1e-6])
    return angles[keep]


@persistent_jit
def _surface_points(part: Part, eta, omega):
    return jax.vmap(surface_point, in_axes=(None, 0, 0))(part, eta, omega)


def part_mesh(part: Part, *, resolution: int = 48) -> trimesh.Trimesh:
    """Watertight triangle mesh of one (unbatched) part in camera coordinates.

    ``resolution`` is the number of samples per quarter turn before merging (~3x that
    many distinct angles per quarter).
    """
    import trimesh

    return trimesh.Trimesh(*part_surface(part, resolution=resolution), process=False)


def part_surface(part: Part, *, resolution: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """:func:`part_mesh`'s vertices (V, 3) and triangles (F, 3), wound outwards, as
    numpy arrays (no trimesh)."""
    if part.batch_shape != ():
        raise ValueError(f"part: got batch shape {part.batch_shape}, expected a single part")
    ((eta, omega),) = check_mesh_size([part], resolution)
    return _surface(part, eta, omega)


def _surface(part: Part, eta: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`part_surface` on the latitudes and longitudes :func:`_angles` gives."""
    n_lat, n_lon = len(eta), len(omega)
    ee, ww = np.meshgrid(eta, omega, indexing="ij")
    grid = np.stack([ee.ravel(), ww.ravel()], -1)
    poles = np.array([[-np.pi / 2, 0.0], [np.pi / 2, 0.0]])
    params = np.concatenate([grid, poles])
    # Padded to a power of two so a few compilations serve every part.
    padded = np.zeros((max(4096, 1 << (len(params) - 1).bit_length()), 2))
    padded[: len(params)] = params
    padded = jnp.asarray(padded, part.size.dtype)
    verts = np.asarray(_surface_points(part, padded[:, 0], padded[:, 1]), np.float64)[: len(params)]
    idx = np.arange(n_lat * n_lon).reshape(n_lat, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    faces = [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    south, north = n_lat * n_lon, n_lat * n_lon + 1
    faces.append(np.stack([np.full(n_lon, south), nxt[0], idx[0]], -1))
    faces.append(np.stack([np.full(n_lon, north), idx[-1], nxt[-1]], -1))
    tris = np.concatenate(faces)
    a, b, c = (verts[tris[:, k]] for k in range(3))
    if np.einsum("ij,ij->", a, np.cross(b, c)) < 0:  # six times the signed volume
        tris = np.ascontiguousarray(tris[:, ::-1])
    return verts, tris


MAX_MESH_TRIANGLES = 50_000_000
"""Most triangles a mesh of parts may have (about 2.4 GB of vertices and triangles in
memory, a 1 GB binary PLY): 300 parts at the command line's default resolution have 44 M;
beyond it, lower the resolution (a part at resolution 512 alone has 38 M)."""

MAX_UNION_TRIANGLES = 10_000_000
"""Most triangles the parts' meshes may have for their Boolean union
(:func:`scene_mesh`): manifold3d and trimesh hold about 220 bytes per input triangle
(measured: 40 overlapping parts, 12.3 M triangles, 3.1 GB resident), so this bound is
about the same 2.4 GB as :data:`MAX_MESH_TRIANGLES`'s."""


def _angles(part: Part, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """A part's latitudes η (poles left out) and longitudes ω on its mesh."""
    e1, e2 = (float(x) for x in np.asarray(part.squareness))
    eta_half = _quarter_angles(e1, resolution)[1:-1]  # exclude 0 (added once) and π/2 (the pole)
    q2 = _quarter_angles(e2, resolution)
    return np.concatenate([-eta_half[::-1], [0.0], eta_half]), np.concatenate(
        [q2[:-1] + k * np.pi / 2 for k in range(4)]
    ) - np.pi


def check_mesh_size(parts, resolution, *, union: bool = False) -> list:
    """``resolution`` checked (an integer >= 4) and the triangles of single ``parts``'
    meshes at it counted, before any is made: at most :data:`MAX_MESH_TRIANGLES`, or
    :data:`MAX_UNION_TRIANGLES` for their ``union``.
    Returns each part's (latitudes, longitudes) (:func:`_angles`)."""
    if not isinstance(resolution, (int, np.integer)) or isinstance(resolution, bool) or resolution < 4:
        raise ValueError(f"resolution: got {resolution!r}, expected an integer >= 4")
    # At least 2(r - 2) + 1 latitudes and 4(r - 1) longitudes each: an absurd resolution is
    # refused before its angles are made.
    limit = MAX_UNION_TRIANGLES if union else MAX_MESH_TRIANGLES
    least = len(parts) * 2 * (2 * int(resolution) - 3) * 4 * (int(resolution) - 1)
    angles = [] if least > limit else [_angles(p, int(resolution)) for p in parts]
    triangles = sum(2 * len(eta) * len(omega) for eta, omega in angles) if angles else least
    if triangles > limit:
        raise ValueError(
            f"resolution: got {resolution!r}, which gives {len(parts)} part(s) {'at least ' * (triangles == least)}"
            f"{triangles} triangles, expected at most {limit}{' for their union' * union} (a lower resolution)"
        )
    return angles


def scene_surface(parts: Part, *, resolution: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Every part's :func:`part_surface`, concatenated (vertices, triangles)."""
    each = _parts_list(parts)
    verts, faces, offset = [], [], 0
    for part, (eta, omega) in zip(each, check_mesh_size(each, resolution)):  # the whole scene, before any part
        v, f = _surface(part, eta, omega)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def scene_mesh(parts: Part, *, resolution: int = 48, union: bool = False) -> trimesh.Trimesh:
    """Mesh of a scene: every part watertight, concatenated; or their Boolean union
    (``union=True``, through manifold3d) as one watertight body."""
    import trimesh

    each = _parts_list(parts)
    if union and len(each) > 1:
        check_mesh_size(each, resolution, union=True)
        meshes = [part_mesh(p, resolution=resolution) for p in each]
        return trimesh.boolean.union(meshes, engine="manifold")  # pyright: ignore[reportReturnType]  # trimesh annotates Geometry; manifold gives a Trimesh
    return trimesh.Trimesh(*scene_surface(parts, resolution=resolution), process=False)


def save_mesh(path, mesh: trimesh.Trimesh | trimesh.Scene) -> None:
    """Write a mesh (or a scene such as :func:`scene_trimesh`'s, as .glb) atomically; the
    format follows the suffix (.ply .obj .stl .glb .off). A mesh goes to PLY through
    :func:`save_ply`, anything else through trimesh's exporters."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"out: got {str(path)!r}, expected a mesh path ending in {', '.join(MESH_SUFFIXES)}")
    if suffix == ".ply" and hasattr(mesh, "faces"):
        save_ply(path, np.asarray(mesh.vertices), np.asarray(mesh.faces))  # pyright: ignore[reportAttributeAccessIssue]  # a Trimesh, not a Scene
        return
    data = mesh.export(file_type=suffix[1:])
    with atomic_write(path, "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())  # pyright: ignore[reportAttributeAccessIssue]  # trimesh's export may be a dict, but not for a mesh suffix


def save_ply(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A triangle mesh as binary little-endian PLY (float32 ``x y z``, ``uchar int``
    index lists: what trimesh writes, read by trimesh, Open3D, MeshLab and Blender),
    atomically. Written with numpy alone, so ``sqparts recover`` need not import trimesh
    (0.4 s of its start-up)."""
    vertices = np.asarray(vertices, "<f4").reshape(-1, 3)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"faces: got indices outside 0..{len(vertices) - 1}, expected indices of the vertices")
    records = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    records["n"] = 3
    records["v"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment sqparts\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with atomic_write(Path(path), "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertices.tobytes())
        f.write(records.tobytes())


def load_mesh(path) -> trimesh.Trimesh:
    """Read a mesh file (any format trimesh reads); scenes are flattened to one mesh."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh: got {str(path)!r}, expected an existing file")
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for bad files
        raise ValueError(f"mesh: got {str(path)!r}, expected a readable mesh ({e})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"mesh: got {str(path)!r} with no triangles, expected a triangle mesh")
    return loaded


def render_mesh(mesh: trimesh.Trimesh, camera: Camera) -> np.ndarray:
    """Ray-cast a mesh (camera coordinates) into a float32 range image, NaN = no return.

    Uses the same rays as the part renderer, so the value is z-depth (range along the ray
    for a scanner).
    """
    origins, directions = (np.asarray(a, np.float64).reshape(-1, 3) for a in camera_rays(camera))
    locations, index_ray, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=True)
    t = np.einsum("ij,ij->i", locations - origins[index_ray], directions[index_ray])
    t /= np.einsum("ij,ij->i", directions[index_ray], directions[index_ray])
    depth = np.full(len(origins), np.inf)
    np.minimum.at(depth, index_ray, np.where(t > 0, t, np.inf))
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(camera.height, camera.width).astype(np.float32)


def part_colors(n: int) -> np.ndarray:
    """(n, 4) uint8 RGBA: part ``i``'s colour, the one ``report.png`` paints its pixels
    (matplotlib's ``tab20``, cycling after 20 parts)."""
    import matplotlib

    rgba = matplotlib.colormaps["tab20"]((np.arange(n) % 20) / 19.999)
    return np.round(np.asarray(rgba) * 255).astype(np.uint8)


def _parts_list(parts: Part) -> list[Part]:
    from ._render import _as_scene

    scene = _as_scene(parts)  # a Part, single or batched, of at least one part
    return [parts] if parts.batch_shape == () else [scene[i] for i in range(len(scene))]


def part_names(parts: Part, names=None) -> list[str]:
    """``names`` (one per part) or ``part_0``, ``part_1``, ... (the index in ``parts.json``)."""
    n = len(_parts_list(parts))
    if names is None:
        return [f"part_{i}" for i in range(n)]
    names = [str(x) for x in names]
    if len(names) != n or len(set(names)) != n:
        raise ValueError(f"names: got {names!r:.80}, expected {n} distinct names (one per part)")
    return names


def scene_trimesh(parts: Part, *, names=None, resolution: int = 32) -> trimesh.Scene:
    """A ``trimesh.Scene`` with one named, coloured, watertight mesh per part.

    Geometry and node names are ``names`` or ``part_<i>``; every vertex has part ``i``'s
    colour of :func:`part_colors` (as in ``report.png``), also set as the material's base
    colour, so the exported GLB (``scene.export("model.glb")``) shows the parts in their
    colours in Blender, three.js and other glTF viewers. Camera frame (OpenCV: y down).
    """
    import trimesh
    import trimesh.visual

    check_mesh_size(_parts_list(parts), resolution)
    meshes = [part_mesh(p, resolution=resolution) for p in _parts_list(parts)]
    colors = part_colors(len(meshes))
    scene = trimesh.Scene()
    for mesh, name, color in zip(meshes, part_names(parts, names), colors):
        material = trimesh.visual.material.PBRMaterial(
            name=name, baseColorFactor=color, roughnessFactor=0.8, metallicFactor=0.0
        )
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile(color, (len(mesh.vertices), 1)))
        mesh.visual.material = material  # pyright: ignore[reportAttributeAccessIssue]  # not declared on ColorVisuals; the glTF export reads it
        mesh.metadata["name"] = name
        scene.add_geometry(mesh, geom_name=name, node_name=name)
    return scene


def scene_open3d(parts: Part, *, resolution: int = 32) -> list:
    """One ``open3d.geometry.TriangleMesh`` per part, with vertex normals and part ``i``'s
    colour of :func:`part_colors` (needs ``pip install sqparts[interop]``)."""
    try:
        import open3d as o3d
    except ImportError as e:
        raise ImportError(f"open3d: got {e}, expected open3d installed (pip install 'sqparts[interop]')") from None
    check_mesh_size(_parts_list(parts), resolution)
    out = []
    for mesh, color in zip(
        (part_mesh(p, resolution=resolution) for p in _parts_list(parts)), part_colors(len(_parts_list(parts)))
    ):
        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
            o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)),
        )
        m.paint_uniform_color(color[:3].astype(np.float64) / 255)
        m.compute_vertex_normals()
        out.append(m)
    return out
