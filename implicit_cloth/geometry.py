"""Reading triangle-mesh files of obstacles (trimesh), checked and reported under the scene key that names them.

(Cloth meshes are read by :func:`implicit_cloth.cloth.from_mesh`, which checks
more: masses, degenerate triangles, manifold edges.)
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .config.validate import fail

__all__ = ["load_obstacle_mesh"]


def load_obstacle_mesh(file: str, key: str = "obstacles.path", given: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of a mesh obstacle's file, read with trimesh (merged vertices).

    Raises
    ------
    SceneError
        Naming ``key``: unreadable file, no triangles, non-finite coordinates.
    """
    import trimesh  # deferred: only mesh obstacles need it

    given = file if given is None else given
    try:
        m = trimesh.load(file, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for bad files
        raise fail(key, f"cannot read mesh file ({type(exc).__name__}: {' '.join(str(exc).split())})",
                   given) from None
    faces = np.asarray(getattr(m, "faces", np.zeros((0, 3))))
    verts = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), dtype=float)
    if faces.ndim != 2 or len(faces) == 0 or faces.shape[1] != 3:
        raise fail(key, "mesh has no triangles", given)
    if not np.isfinite(verts).all():
        raise fail(key, "mesh has non-finite coordinates", given)
    return verts, faces.astype(np.int64)
