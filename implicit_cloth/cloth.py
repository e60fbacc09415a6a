"""Cloth geometry and spring topology: rectangular grids and triangle meshes.

Everything here runs once per cloth (not per step) and is vectorised.

Grid convention: ``resolution = [nx, ny]`` vertices, vertex index ``j*nx + i``
with ``i`` along the width and ``j`` along the height; row ``j = ny-1`` is the
top. Springs follow the classic mass-spring cloth (Provot 1995):

* structural: grid neighbours (mesh: every edge),
* shear: both diagonals of every cell (mesh: none, triangle edges carry shear),
* bend: every other vertex along rows and columns (mesh: across every interior
  edge, joining the two vertices opposite it).

Mesh files are checked as they are read (:func:`from_mesh`): defects that
leave nothing sensible to simulate are a :class:`~implicit_cloth.errors.SceneError`
naming ``cloth.mesh``; defects that can be worked around (zero-area triangles,
duplicate vertices, non-manifold edges) are a
:class:`~implicit_cloth.errors.MeshWarning` and the cloth is built anyway.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import MeshWarning, SceneError

#: Mesh file extensions read (through trimesh), case-insensitive.
MESH_FORMATS: tuple[str, ...] = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")

#: A triangle counts as zero-area (degenerate) when its area is at most this times its longest edge squared
#: (a height below 2e-12 of its longest side), or when it repeats a vertex.
DEGENERATE_AREA = 1e-12


@dataclass
class ClothGeometry:
    """Vertices, triangles and springs of a cloth.

    Attributes
    ----------
    positions : (N, 3) float array
        Initial vertex positions, m.
    faces : (T, 3) int array
        Triangles (vertex indices), counter-clockwise.
    springs : dict of str -> (S_k, 2) int array
        Vertex pairs of each spring kind.
    grid_shape : (nx, ny) or None
        Set for grid cloths, where corner names can be used for pins.
    """

    positions: np.ndarray
    faces: np.ndarray
    springs: dict[str, np.ndarray]
    grid_shape: tuple[int, int] | None = None

    @property
    def n_vertices(self) -> int:
        return len(self.positions)

    def corner(self, name: str, where: str = "cloth.pins") -> int:
        """Index of a named corner of a grid cloth (``top_left`` is ``i = 0, j = ny-1``)."""
        if self.grid_shape is None:
            raise SceneError(f"{where}: corner name {name!r} only applies to a grid cloth; use vertex indices")
        nx, ny = self.grid_shape
        return {
            "bottom_left": 0,
            "bottom_right": nx - 1,
            "top_left": (ny - 1) * nx,
            "top_right": ny * nx - 1,
        }[name]


def combine(pieces: list[ClothGeometry]) -> ClothGeometry:
    """Several pieces as one cloth: vertices in order, faces and springs offset by the vertices before them.

    One piece is returned as it is (a grid keeps its ``grid_shape``); the union of several has none.
    """
    if len(pieces) == 1:
        return pieces[0]
    start = np.cumsum([0] + [g.n_vertices for g in pieces])
    kinds = [k for k in ("structural", "shear", "bend") if any(k in g.springs for g in pieces)]
    springs = {k: np.concatenate([g.springs[k] + o for g, o in zip(pieces, start) if k in g.springs]).reshape(-1, 2)
               for k in kinds}
    return ClothGeometry(np.concatenate([g.positions for g in pieces]),
                         np.concatenate([g.faces + o for g, o in zip(pieces, start)]), springs)


def triangle_areas(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle, m^2: ``|(x1 - x0) x (x2 - x0)| / 2``."""
    p = positions[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def degenerate_faces(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean mask of the zero-area triangles (see :data:`DEGENERATE_AREA`), (T,)."""
    p = positions[faces]
    longest2 = np.max([np.einsum("ij,ij->i", d, d) for d in (p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2])],
                      axis=0)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    return repeated | (triangle_areas(positions, faces) <= DEGENERATE_AREA * longest2)


def lumped_areas(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area associated with each vertex, m^2: a third of each adjacent triangle's area."""
    a = triangle_areas(positions, faces)
    return np.bincount(faces.ravel(), weights=np.repeat(a / 3.0, 3), minlength=len(positions))


def grid(size: tuple[float, float], resolution: tuple[int, int], center=(0.0, 0.0, 0.0),
         plane: str = "xz", kinds=("structural", "shear", "bend")) -> ClothGeometry:
    """A rectangular grid cloth.

    Parameters
    ----------
    size : (w, h)
        Width and height, m.
    resolution : (nx, ny)
        Vertices along the width and the height (each >= 2).
    center : (3,)
        Centre of the rectangle, m.
    plane : {"xy", "xz", "yz"}
        Plane the cloth lies in; width runs along the first axis, height along
        the second ("xy" lies flat with z up, "xz" hangs vertically).
    kinds : iterable of str
        Spring kinds to build.
    """
    w, h = float(size[0]), float(size[1])
    nx, ny = int(resolution[0]), int(resolution[1])
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny))  # (ny, nx): index j*nx + i
    u = (ii.ravel() / (nx - 1) - 0.5) * w
    v = (jj.ravel() / (ny - 1) - 0.5) * h
    axes = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}[plane]
    pos = np.zeros((nx * ny, 3))
    pos[:, axes[0]] = u
    pos[:, axes[1]] = v
    with np.errstate(over="ignore"):   # an overflow is reported by Model (cloth.center)
        pos += np.asarray(center, dtype=float)

    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()       # cell bottom-left, bottom-right
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()         # cell top-left, top-right
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int64)

    def pairs(p, q):
        return np.stack([p.ravel(), q.ravel()], 1).astype(np.int64)

    springs: dict[str, np.ndarray] = {}
    kinds = tuple(kinds)
    if "structural" in kinds:
        springs["structural"] = np.concatenate([pairs(idx[:, :-1], idx[:, 1:]), pairs(idx[:-1, :], idx[1:, :])])
    if "shear" in kinds:
        springs["shear"] = np.concatenate([pairs(a, d), pairs(b, c)])
    if "bend" in kinds:
        springs["bend"] = np.concatenate([pairs(idx[:, :-2], idx[:, 2:]), pairs(idx[:-2, :], idx[2:, :])])
    return ClothGeometry(pos, faces, springs, grid_shape=(nx, ny))


def mesh_springs(faces: np.ndarray, kinds=("structural", "bend"), skip: np.ndarray | None = None
                 ) -> dict[str, np.ndarray]:
    """Springs of a triangle mesh: structural on every edge, bend across every interior edge.

    A bend spring joins the two vertices opposite an edge shared by exactly two
    triangles. Edges shared by more than two triangles (non-manifold) get no
    bend spring. A face that repeats a vertex (``[a, a, b]``), and a face
    marked in ``skip`` (a zero-area triangle, see :func:`degenerate_faces`),
    takes no part in the bend springs, but its edges between distinct
    vertices get structural springs; no spring joins a vertex to itself.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e_all = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    e_all = e_all[e_all[:, 0] != e_all[:, 1]]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    if skip is not None:
        keep &= ~np.asarray(skip, dtype=bool)
    faces = faces[keep]
    # each proper face's three edges (sorted vertex pair) and the vertex opposite each
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    opp = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    e.sort(axis=1)
    uniq, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    springs: dict[str, np.ndarray] = {}
    if "structural" in kinds:
        springs["structural"] = np.unique(e_all, axis=0).reshape(-1, 2)
    if "bend" in kinds:
        interior = counts[inverse] == 2
        order = np.argsort(inverse[interior], kind="stable")
        o = opp[interior][order].reshape(-1, 2)
        o = o[o[:, 0] != o[:, 1]]
        springs["bend"] = np.unique(np.sort(o, axis=1), axis=0)
    if "shear" in kinds:
        springs["shear"] = np.zeros((0, 2), dtype=np.int64)
    return springs


def from_mesh(path: str, scale: float = 1.0, translation=(0.0, 0.0, 0.0),
              kinds=("structural", "bend")) -> ClothGeometry:
    """A cloth from a triangle mesh file (OBJ, PLY, STL, glTF, OFF; see :data:`MESH_FORMATS`), read with trimesh.

    Vertices are used as they are in the file (not merged, not dropped, not split at UV seams: vertex ``k``
    of the file is vertex ``k`` of the cloth, and pins index the file's vertices; OBJ files are read by
    :func:`implicit_cloth.objfile.read_obj` for that), multiplied by ``scale`` and shifted by ``translation``
    (m).

    Raises
    ------
    SceneError
        Naming ``cloth.mesh``: the file is missing, not a file, empty,
        unreadable, of an unsupported format or not parseable; it has no
        triangles, a face index out of range, a non-finite coordinate; or a
        vertex would have no mass (see :func:`check_mesh`). Naming
        ``cloth.scale``: scaled coordinates overflow.

    Warns
    -----
    MeshWarning
        Zero-area triangles, duplicate vertices, non-manifold edges.
    """
    if not os.path.exists(path):
        raise SceneError(f"cloth.mesh: file not found, got {path!r}")
    if not os.path.isfile(path):
        raise SceneError(f"cloth.mesh: not a file (a directory?), got {path!r}")
    ext = Path(path).suffix.lower()
    if ext not in MESH_FORMATS:
        what = f"unsupported mesh format {ext!r}" if ext else "no file extension to tell the mesh format"
        raise SceneError(f"cloth.mesh: {what} (supported: {', '.join(MESH_FORMATS)}), got {path!r}")
    try:
        with open(path, "rb") as f:
            empty = not f.read(1)
    except OSError as exc:
        raise SceneError(f"cloth.mesh: cannot read mesh file ({exc.strerror or exc}), got {path!r}") from None
    if empty:
        raise SceneError(f"cloth.mesh: file is empty, got {path!r}")

    if ext == ".obj":     # read here: trimesh would drop unused vertices and split UV seams (renumbering)
        from .objfile import read_obj

        verts, faces = read_obj(path)
    else:
        verts, faces = _load_with_trimesh(path, ext)
    if faces.size == 0:
        raise SceneError(f"cloth.mesh: mesh has no triangles, got {path!r}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise SceneError(f"cloth.mesh: faces are not triangles of vertex indices (shape {faces.shape}, "
                         f"{faces.dtype}), got {path!r}")
    faces = faces.astype(np.int64)
    out_of_range = (faces < 0) | (faces >= len(verts))
    if out_of_range.any():
        bf = int(np.flatnonzero(out_of_range.any(axis=1))[0])
        raise SceneError(f"cloth.mesh: face {bf} = {faces[bf].tolist()} refers to vertex "
                         f"{int(faces[bf][out_of_range[bf]][0])}, which is not in the file (it has {len(verts)} "
                         f"vertices, 0 to {len(verts) - 1}), got {path!r}")
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        v = int(np.flatnonzero(bad)[0])
        raise SceneError(f"cloth.mesh: vertex {v} has a non-finite coordinate {verts[v].tolist()} "
                         f"({int(bad.sum())} such vertices), got {path!r}")
    with np.errstate(over="ignore", invalid="ignore"):
        pos = verts * float(scale) + np.asarray(translation, dtype=float)
    if not np.isfinite(pos).all():
        raise SceneError(f"cloth.scale: scaled and translated mesh coordinates are not finite (largest file "
                         f"coordinate {np.abs(verts).max():g}), got {scale}")
    degenerate = check_mesh(pos, faces, path, raw_positions=verts)
    return ClothGeometry(pos, faces, mesh_springs(faces, kinds, skip=degenerate), grid_shape=None)


def mesh_uv(path: str, faces: np.ndarray, where: str = "cloth.membrane") -> np.ndarray:
    """Texture coordinates of the triangles' corners of a mesh file read by :func:`from_mesh` (the same
    ``faces``), (T, 3, 2): an OBJ's ``vt`` of each face corner, another format's per-vertex UVs (trimesh's
    ``visual.uv``).

    Raises
    ------
    SceneError
        Naming ``where`` and the file: the file has no texture coordinates (for every face corner).
    """
    ext = Path(path).suffix.lower()
    uv: np.ndarray | None = None
    if ext == ".obj":
        from .objfile import read_obj_uv

        uv = read_obj_uv(path)
        if uv is not None and uv.shape[0] != len(faces):
            uv = None
    else:
        import trimesh  # deferred: only mesh cloths need it

        try:
            loaded = trimesh.load(path, file_type=ext[1:], force="mesh", process=False)
            per_vertex = getattr(getattr(loaded, "visual", None), "uv", None)
        except Exception:  # the geometry was read already; a failure here means no usable UVs
            per_vertex = None
        if per_vertex is not None:
            per_vertex = np.asarray(per_vertex, dtype=float)
            if per_vertex.ndim == 2 and per_vertex.shape[1] >= 2 and len(per_vertex) > int(faces.max()):
                uv = per_vertex[:, :2][faces]
    if uv is None or not np.isfinite(uv).all():
        raise SceneError(f"{where}: the mesh file has no texture coordinates (UVs) for every face corner, which "
                         f"the membrane needs for its rest (u, v) directions (warp and weft); add UVs to the "
                         f"file or use [cloth.springs], got {path!r}")
    return uv


def _load_with_trimesh(path: str, ext: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # deferred: only mesh cloths need it

    try:
        loaded = trimesh.load(path, file_type=ext[1:], force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        hint = "; a face probably refers to a vertex that is not in the file" if isinstance(exc, IndexError) else ""
        raise SceneError(f"cloth.mesh: cannot read mesh file {path!r} as {ext[1:].upper()} "
                         f"({type(exc).__name__}: {' '.join(str(exc).split())}{hint})") from None
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))))
    verts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
    return verts, faces


def _first(indices: np.ndarray, k: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:k])
    return shown + (", ..." if len(indices) > k else "")


def check_mesh(positions: np.ndarray, faces: np.ndarray, path: str = "",
               raw_positions: np.ndarray | None = None) -> np.ndarray:
    """Check a mesh cloth's triangles: raise for what cannot be simulated, warn for what can.

    Returns the mask of zero-area triangles (:func:`degenerate_faces`).

    Errors (:class:`SceneError` naming ``cloth.mesh``, the first offending
    vertex and the reason): every triangle has zero area; a vertex is in no
    triangle (unreferenced) or only in zero-area triangles, so it would get no
    mass. Warnings (:class:`MeshWarning`, the run goes on): zero-area triangles
    (they add no mass and no bend springs; their edges still get structural
    springs), duplicate vertices (same coordinates in ``raw_positions``,
    default ``positions``; not merged), non-manifold edges (in more than two
    triangles of positive area; no bend spring).
    """
    n = len(positions)
    where = f", got {path!r}" if path else ""
    in_file = f" (file {path!r})" if path else ""
    degenerate = degenerate_faces(positions, faces)
    if degenerate.all():
        raise SceneError(f"cloth.mesh: every triangle has zero area ({len(faces)} triangles), so the cloth "
                         f"would have no mass{where}")
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    good = np.zeros(n, dtype=bool)
    good[faces[~degenerate].ravel()] = True
    unreferenced = np.flatnonzero(~used)
    if len(unreferenced):
        raise SceneError(f"cloth.mesh: vertex {unreferenced[0]} is in no triangle (unreferenced), so it would have "
                         f"no mass; remove it from the file ({len(unreferenced)} such vertices: "
                         f"{_first(unreferenced)}){where}")
    only_degenerate = np.flatnonzero(used & ~good)
    if len(only_degenerate):
        v = only_degenerate[0]
        fs = np.flatnonzero((faces == v).any(axis=1))
        raise SceneError(f"cloth.mesh: vertex {v} is only in zero-area triangles (faces {_first(fs)}), so it would "
                         f"have no mass; fix or remove those triangles ({len(only_degenerate)} such vertices: "
                         f"{_first(only_degenerate)}){where}")
    if degenerate.any():
        fs = np.flatnonzero(degenerate)
        warnings.warn(f"cloth.mesh: {len(fs)} zero-area triangles (faces {_first(fs)}; first = "
                      f"{faces[fs[0]].tolist()}); they add no mass and no bend springs{in_file}", MeshWarning,
                      stacklevel=5)
    raw = positions if raw_positions is None else raw_positions
    _, first_index, inverse = np.unique(raw, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    dup = np.flatnonzero(first_index[inverse] != np.arange(n))
    if len(dup):
        v = dup[0]
        warnings.warn(f"cloth.mesh: {len(dup)} duplicate vertices (vertex {v} has the coordinates of vertex "
                      f"{first_index[inverse[v]]}); vertices are not merged, so the cloth is not joined "
                      f"there{in_file}", MeshWarning, stacklevel=5)
    proper = faces[~degenerate]
    e = np.sort(np.concatenate([proper[:, [0, 1]], proper[:, [1, 2]], proper[:, [2, 0]]]), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    many = np.flatnonzero(counts > 2)
    if len(many):
        a, b = edges[many[0]]
        warnings.warn(f"cloth.mesh: {len(many)} non-manifold edges (edge {a}-{b} is in {counts[many[0]]} "
                      f"triangles); they get no bend spring{in_file}", MeshWarning, stacklevel=5)
    return degenerate
