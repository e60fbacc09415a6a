"""A Wavefront OBJ reader that keeps the file's vertex numbering (for mesh cloths).

General-purpose loaders (trimesh among them) renumber an OBJ's vertices: they drop vertices no face uses and
split a vertex wherever its faces give it different texture coordinates or normals (``f v/vt/vn``), so a
cloth with a UV seam would come apart along it, and pins would point at other vertices. Here vertex ``k`` of
the file (``v`` lines, counted from 1) is vertex ``k - 1`` of the cloth, whatever the faces' ``vt`` and ``vn``
indices say; faces with more than three corners are split into a fan of triangles around their first corner.
Other statements (``vt``, ``vn``, ``o``, ``g``, ``s``, ``usemtl``, ``mtllib``, ``l``, ``p``) are ignored; the
texture coordinates of the faces' corners are read by :func:`read_obj_uv` (the membrane's warp and weft).
"""

from __future__ import annotations

import os

import numpy as np

from .errors import SceneError


def _index(token: str, n: int, line_no: int, path: str) -> int:
    head = token.split("/", 1)[0]
    try:
        k = int(head)
    except ValueError:
        raise SceneError(f"cloth.mesh: line {line_no}: face corner {token!r} is not a vertex index, got "
                         f"{path!r}") from None
    if k == 0:
        raise SceneError(f"cloth.mesh: line {line_no}: vertex index 0 (OBJ counts from 1), got {path!r}")
    return k - 1 if k > 0 else n + k        # negative: relative to the vertices read so far


def read_obj(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (T, 3) of an OBJ file in the file's own vertex numbering.

    Raises
    ------
    SceneError
        Naming ``cloth.mesh`` and the line: an unreadable file, a ``v`` line without three numbers, a face with
        fewer than three corners or a corner that is not an index. (Indices beyond the vertices are left to the
        caller's range check, which names the face.)
    """
    path = str(path)
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.readlines()
    except OSError as exc:
        raise SceneError(f"cloth.mesh: cannot read mesh file ({exc.strerror or exc}), got {path!r}") from None
    for line_no, raw in enumerate(lines, 1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            try:
                verts.append([float(x) for x in parts[1:4]])
            except ValueError:
                verts.append([])
            if len(verts[-1]) != 3:
                raise SceneError(f"cloth.mesh: line {line_no}: a vertex needs three numbers x y z, got "
                                 f"{raw.strip()!r} in {path!r}")
        elif parts[0] == "f":
            corners = [_index(t, len(verts), line_no, path) for t in parts[1:]]
            if len(corners) < 3:
                raise SceneError(f"cloth.mesh: line {line_no}: a face needs at least three corners, got "
                                 f"{raw.strip()!r} in {path!r}")
            faces.extend([corners[0], corners[k], corners[k + 1]] for k in range(1, len(corners) - 1))
    return np.array(verts, float).reshape(-1, 3), np.array(faces, np.int64).reshape(-1, 3)


def read_obj_uv(path: str | os.PathLike[str]) -> np.ndarray | None:
    """Texture coordinates ``(u, v)`` of every triangle's corners, (T, 3, 2), in :func:`read_obj`'s triangles
    (the same fans), from the ``vt`` lines and the faces' ``v/vt`` corners; None if a face corner has no
    texture coordinate (or one that is not a ``vt`` of the file)."""
    path = str(path)
    vts: list[list[float]] = []
    out: list[list[list[float]]] = []
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.readlines()
    except OSError:
        return None
    for raw in lines:
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "vt":
            try:
                vts.append([float(x) for x in parts[1:3]])
            except ValueError:
                return None
            if len(vts[-1]) != 2:
                return None
        elif parts[0] == "f":
            corners: list[list[float]] = []
            for t in parts[1:]:
                fields = t.split("/")
                if len(fields) < 2 or not fields[1]:
                    return None
                try:
                    k = int(fields[1])
                except ValueError:
                    return None
                k = k - 1 if k > 0 else len(vts) + k
                if not 0 <= k < len(vts):
                    return None
                corners.append(vts[k])
            out.extend([corners[0], corners[m], corners[m + 1]] for m in range(1, len(corners) - 1))
    return np.array(out, float).reshape(-1, 3, 2)
