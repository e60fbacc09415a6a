"""Cloth geometry and spring topology: rectangular grids and triangle meshes.

Everything here runs once per cloth (not per step) and is vectorised.

Grid convention: ``resolution = [nx, ny]`` vertices, vertex index ``j*nx + i``
with ``i`` along the width and ``j`` along the height; row ``j = ny-1`` is the
top. Springs follow the classic mass-spring cloth (Provot 1995):

* structural: grid neighbours (mesh: every edge),
* shear: both diagonals of every cell (mesh: none, triangle edges carry shear),
* bend: every other vertex along rows and columns (mesh: across every interior
  edge, joining the two vertices opposite it).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .errors import SceneError


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


def triangle_areas(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle, m^2: ``|(x1 - x0) x (x2 - x0)| / 2``."""
    p = positions[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


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


def mesh_springs(faces: np.ndarray, kinds=("structural", "bend")) -> dict[str, np.ndarray]:
    """Springs of a triangle mesh: structural on every edge, bend across every interior edge.

    A bend spring joins the two vertices opposite an edge shared by exactly two
    triangles. Edges shared by more than two triangles (non-manifold) get no
    bend spring.
    """
    faces = np.asarray(faces, dtype=np.int64)
    # each face's three edges (sorted vertex pair) and the vertex opposite each
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    opp = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    e.sort(axis=1)
    uniq, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    springs: dict[str, np.ndarray] = {}
    if "structural" in kinds:
        springs["structural"] = uniq
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
    """A cloth from any triangle mesh file trimesh reads (OBJ, PLY, STL, glTF, OFF).

    Vertices are used as they are in the file (not merged), multiplied by
    ``scale`` and shifted by ``translation`` (m).
    """
    import trimesh  # deferred: only mesh cloths need it

    if not os.path.isfile(path):
        raise SceneError(f"cloth.mesh: file not found, got {path!r}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise SceneError(f"cloth.mesh: cannot read mesh file {path!r} ({type(exc).__name__}: {exc})") from None
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    verts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
    if len(faces) == 0:
        raise SceneError(f"cloth.mesh: mesh has no triangles, got {path!r}")
    pos = verts * float(scale) + np.asarray(translation, dtype=float)
    return ClothGeometry(pos, faces, mesh_springs(faces, kinds), grid_shape=None)
