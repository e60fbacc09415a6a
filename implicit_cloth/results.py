"""A run's output read back for export and render: frames, pieces, normals, UVs and the obstacles' meshes.

:func:`read_run` loads ``RUN_DIR/trajectory.npz`` and the scene stored in ``RUN_DIR/report.json``. The obstacles
are the scene's validated ``[[obstacles]]`` tables, each turned into a triangle mesh in the shape's local frame
(the frame :mod:`implicit_cloth.collision.shapes` defines) and placed at any time by the collision code's own
rigid motion (:func:`implicit_cloth.collision.shapes.placement`: velocity, angular velocity or keyframes), so an
exported or rendered obstacle is where the simulation had it.

The drawn surfaces are inscribed in the true ones (an icosphere's vertices on the sphere, the cone's rim polygon
on its base circle), so a cloth resting on an obstacle is never drawn inside it.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import InputError, SceneError
from .errors import show as _fmt

#: Shapes with a drawable surface (every shape the collision code knows).
DRAWN_SHAPES: tuple[str, ...] = ("sphere", "box", "cone", "capsule", "plane", "mesh")


class ObstacleWarning(UserWarning):
    """An obstacle of the stored scene cannot be turned into a mesh; the output is made without it."""


@dataclass
class Obstacle:
    """One obstacle as a mesh in its local frame and its rigid motion.

    ``vertices`` (V, 3) m and ``faces`` (T, 3) in the shape's local frame; :meth:`pose` and :meth:`world` place
    them at a time (the collision code's :class:`~implicit_cloth.collision.shapes.RigidMotion`).
    """

    name: str
    shape: str
    vertices: np.ndarray
    faces: np.ndarray
    motion: Any

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Centre (3,) m and rotation matrix (3, 3) at time ``t`` (s)."""
        c, R = self.motion.pose(float(t))
        return np.asarray(c, float), np.asarray(R, float)

    def world(self, t: float) -> np.ndarray:
        """Vertices (V, 3) in world coordinates at time ``t``, m."""
        return np.asarray(self.motion.to_world(self.vertices, float(t)), float)


@dataclass
class Run:
    """A run's frames and scene.

    Attributes
    ----------
    positions : (F, N, 3) float array, m;  times : (F,) s;  faces : (T, 3) int
    scene : the normalised scene (``report["scene"]``), or None when there is no readable report
    fps : frames per second of the run's time line (the scene's ``frame_rate``, or ``1 / dt`` when every step is
        kept); a frame's time code is ``times * fps``
    """

    positions: np.ndarray
    times: np.ndarray
    faces: np.ndarray
    scene: Mapping[str, Any] | None
    fps: float
    _obstacles: list[Obstacle] | None = field(default=None, repr=False)
    #: each ``[[cloth]]`` piece's vertex range ``(start, stop)`` (the report's ``pieces``), else None
    piece_ranges: list[tuple[int, int]] | None = None

    @property
    def n_frames(self) -> int:
        return len(self.positions)

    def time_codes(self) -> np.ndarray:
        """Each frame's time code, ``times * fps`` (0, 1, 2, ... for evenly kept frames)."""
        return self.times * self.fps

    def extent(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and half-size of the box around the cloth over the whole run, m."""
        flat = self.positions.reshape(-1, 3)
        lo, hi = flat.min(0), flat.max(0)
        return (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 1e-3)

    def _cloths(self) -> list[Mapping[str, Any]]:
        """The stored scene's cloth pieces (``[cloth]`` is one, ``[[cloth]]`` several); [] without a scene."""
        cloth = (self.scene or {}).get("cloth") or {}
        pieces = cloth if isinstance(cloth, list) else [cloth]
        return [c for c in pieces if isinstance(c, Mapping)]

    def pieces(self) -> list[np.ndarray]:
        """Vertex indices of each piece of cloth: the scene's ``[[cloth]]`` pieces in order (their vertex ranges in
        the report), else each connected piece (joined by triangles), largest first."""
        r = self.piece_ranges
        if r and r[0][0] == 0 and r[-1][1] == self.positions.shape[1] and all(a < b for a, b in r):
            return [np.arange(a, b) for a, b in r]
        return cloth_pieces(self.faces, self.positions.shape[1])

    def uvs(self) -> np.ndarray | None:
        """Per-vertex texture coordinates (N, 2) of grid cloths (``i / (nx - 1), j / (ny - 1)`` of each piece),
        else None."""
        cloths = self._cloths()
        if not cloths or any(c.get("kind") != "grid" for c in cloths):
            return None
        out = []
        for c in cloths:
            nx, ny = (int(r) for r in c["resolution"])
            jj, ii = np.divmod(np.arange(nx * ny), nx)
            out.append(np.stack([ii / (nx - 1), jj / (ny - 1)], axis=1))
        uv = np.concatenate(out)
        return uv if len(uv) == self.positions.shape[1] else None

    def rest_positions(self) -> np.ndarray:
        """The cloth's rest shape (N, 3), m: rebuilt from the stored scene (grids or mesh files), else frame 0."""
        parts = []
        try:
            from . import cloth as builders

            for c in self._cloths():
                if c.get("kind") == "grid":
                    geo = builders.grid(c["size"], c["resolution"], c["center"], c["plane"])
                elif c.get("kind") == "mesh":
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        geo = builders.from_mesh(c["mesh"], c["scale"], c["translation"])
                else:
                    return self.positions[0]
                parts.append(geo.positions)
        except (SceneError, KeyError, TypeError, ValueError, OSError):
            return self.positions[0]
        rest = np.concatenate(parts) if parts else self.positions[0]
        return rest if rest.shape == self.positions.shape[1:] else self.positions[0]

    def strain(self, frames: list[int]) -> np.ndarray:
        """Per-vertex strain (F, N) at the frames: the largest ``|x_ij| / L_ij - 1`` of the triangle edges at
        each vertex, ``L`` from :meth:`rest_positions` (stretch > 0, compression < 0 shown only where no edge
        is stretched)."""
        e = np.unique(np.sort(np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]],
                                              self.faces[:, [2, 0]]]), axis=1), axis=0)
        rest = np.linalg.norm(np.diff(self.rest_positions()[e], axis=1)[:, 0], axis=1)
        rest = np.where(rest > 0, rest, np.inf)
        out = np.full((len(frames), self.positions.shape[1]), -np.inf)
        for k, f in enumerate(frames):
            length = np.linalg.norm(np.diff(self.positions[f][e], axis=1)[:, 0], axis=1)
            s = length / rest - 1.0
            np.maximum.at(out[k], e[:, 0], s)
            np.maximum.at(out[k], e[:, 1], s)
        return np.where(np.isfinite(out), out, 0.0)

    def speed(self, frames: list[int]) -> np.ndarray:
        """Per-vertex speed (F, N) at the frames, m/s, by central differences of the kept frames (one-sided at
        the ends; 0 for a single frame)."""
        n = self.n_frames
        out = np.zeros((len(frames), self.positions.shape[1]))
        for k, f in enumerate(frames):
            a, b = max(f - 1, 0), min(f + 1, n - 1)
            if b > a and self.times[b] > self.times[a]:
                out[k] = np.linalg.norm(self.positions[b] - self.positions[a], axis=1) / (self.times[b] - self.times[a])
        return out

    def obstacles(self) -> list[Obstacle]:
        """The scene's obstacles as meshes (those that cannot be built are left out with an ObstacleWarning)."""
        if self._obstacles is None:
            specs = (self.scene or {}).get("obstacles") or []
            self._obstacles = [ob for k, spec in enumerate(specs)
                               if (ob := obstacle_mesh(spec, k, self.extent())) is not None]
        return self._obstacles


def cloth_pieces(faces: np.ndarray, n: int) -> list[np.ndarray]:
    """Vertex indices of each connected component of the triangle graph, largest first (ties: lowest index)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64).reshape(-1, 3)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    groups = [np.flatnonzero(labels == lab) for lab in np.unique(labels)]
    return sorted(groups, key=lambda g: (-len(g), int(g[0])))


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (..., N, 3) of positions (..., N, 3); (0, 0, 1) where undefined."""
    from scipy.sparse import csr_matrix

    p = np.asarray(positions, float)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    n_v, n_t = p.shape[-2], len(f)
    tri = np.cross(p[..., f[:, 1], :] - p[..., f[:, 0], :], p[..., f[:, 2], :] - p[..., f[:, 0], :])
    incidence = csr_matrix((np.ones(3 * n_t), (f.T.ravel(), np.tile(np.arange(n_t), 3))), shape=(n_v, n_t))
    lead = p.shape[:-2]
    flat = np.moveaxis(tri.reshape(-1, n_t, 3), 1, 0).reshape(n_t, -1)          # (T, F*3)
    n = np.moveaxis(np.asarray(incidence @ flat).reshape(n_v, -1, 3), 0, 1).reshape(*lead, n_v, 3)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    out = np.divide(n, norm, out=np.zeros_like(n), where=norm > 1e-300)
    out[..., 2] = np.where(norm[..., 0] > 1e-300, out[..., 2], 1.0)
    return out


def obstacle_mesh(spec: Mapping[str, Any], k: int, extent: tuple[np.ndarray, float]) -> Obstacle | None:
    """The ``k``-th obstacle table of a stored (validated) scene as an :class:`Obstacle`; None with a warning.

    ``extent`` = (centre, half-size) of the cloth's motion: a plane is drawn as a square 4 half-sizes wide
    around the point of the plane nearest that centre (at the run's start).
    """
    from .collision.shapes import placement

    shape = spec.get("shape") if isinstance(spec, Mapping) else None
    if shape not in DRAWN_SHAPES:
        warnings.warn(f"obstacles[{k}]: shape {shape!r} is not drawn (drawn: {', '.join(DRAWN_SHAPES)})",
                      ObstacleWarning, stacklevel=3)
        return None
    try:
        spec = dict(spec)
        try:            # a stored scene's tables are validated already (and re-validating a keyframed one fails)
            motion = placement(spec)
        except KeyError:            # a hand-written table: validated (defaults filled in) as a scene's
            from .obstacles import validate_obstacles

            spec = validate_obstacles([spec])[0]
            motion = placement(spec)
        if shape == "plane":
            c, half = extent
            q = motion.to_local(np.asarray(c, float)[None], 0.0)[0]
            s = 2.0 * half
            verts = np.array([[q[0] + a * s, q[1] + b * s, 0.0] for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            faces = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
        else:
            verts, faces = _local_mesh(spec)
    except (SceneError, KeyError, TypeError, ValueError, OSError) as exc:
        warnings.warn(f"obstacles[{k}]: a {shape!r} obstacle is not drawn ({type(exc).__name__}: {exc})",
                      ObstacleWarning, stacklevel=3)
        return None
    return Obstacle(f"obstacle_{k}_{shape}", shape, np.asarray(verts, float), np.asarray(faces, np.int64), motion)


def _local_mesh(spec: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a bounded obstacle in its local frame (as the collision shapes define it)."""
    import trimesh

    from .collision.shapes import CONE_RIM_SEGMENTS

    shape = spec["shape"]
    if shape == "sphere":
        m = trimesh.creation.icosphere(subdivisions=4, radius=float(spec["radius"]))
    elif shape == "box":
        m = trimesh.creation.box(extents=[float(s) for s in spec["size"]])
    elif shape == "cone":        # base centre at the origin, apex on +z: trimesh's convention too
        m = trimesh.creation.cone(radius=float(spec["radius"]), height=float(spec["height"]),
                                  sections=CONE_RIM_SEGMENTS)
    elif shape == "capsule":     # centred, axis z, height = the segment's length
        m = trimesh.creation.capsule(height=float(spec["height"]), radius=float(spec["radius"]), count=[32, 32])
    else:   # mesh: the file's coordinates times scale (the collision code's MeshShape)
        from .geometry import load_obstacle_mesh

        verts, faces = load_obstacle_mesh(spec["path"])
        return np.asarray(verts, float) * float(spec["scale"]), np.asarray(faces, np.int64)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def _report_scene(run_dir: Path) -> tuple[Mapping[str, Any] | None, list[tuple[int, int]] | None]:
    """The stored scene and the pieces' vertex ranges of ``RUN_DIR/report.json`` (None where missing)."""
    try:
        report = json.loads((run_dir / "report.json").read_text())
    except (OSError, ValueError):
        return None, None
    if not isinstance(report, Mapping):
        return None, None
    scene = report.get("scene")
    ranges = None
    try:
        ranges = [(int(p["vertices"][0]), int(p["vertices"][1])) for p in report["pieces"]]
    except (KeyError, TypeError, ValueError, IndexError):
        pass
    return (scene if isinstance(scene, Mapping) else None), ranges


def run_fps(times: np.ndarray, scene: Mapping[str, Any] | None) -> float:
    """Frames per second of a run's time line: the scene's frame rate, or 1 / dt when every step is kept."""
    sim = (scene or {}).get("simulation") or {}
    rate, dt = sim.get("frame_rate"), sim.get("dt")
    if isinstance(rate, (int, float)) and isinstance(dt, (int, float)) and rate > 0 and dt > 0:
        return float(min(rate, 1.0 / dt))
    if len(times) > 1 and times[-1] > times[0]:
        return float((len(times) - 1) / (times[-1] - times[0]))
    return 30.0


def read_run(run_dir: str | os.PathLike[str]) -> Run:
    """Read ``RUN_DIR/trajectory.npz`` (required) and the scene of ``RUN_DIR/report.json`` (optional).

    Raises
    ------
    InputError
        If the trajectory is missing or unreadable (one line naming it).
    """
    run_dir = Path(run_dir)
    p = run_dir / "trajectory.npz"
    if not p.is_file():
        raise InputError(f"RUN_DIR: no trajectory.npz (not a run output directory), got {_fmt(str(run_dir))}")
    try:
        with np.load(p) as z:
            positions = np.asarray(z["positions"], float)
            times = np.asarray(z["times"], float)
            faces = np.asarray(z["faces"], np.int64)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"RUN_DIR: cannot read {p} ({' '.join(str(exc).split())}), got {_fmt(str(run_dir))}"
                         ) from None
    if positions.ndim != 3 or positions.shape[0] == 0 or len(times) != len(positions):
        raise InputError(f"RUN_DIR: {p} holds no frames (positions {positions.shape}), got {_fmt(str(run_dir))}")
    from .files import check_pair

    check_pair(run_dir)
    scene, ranges = _report_scene(run_dir)
    fps = run_fps(times, scene)
    if not math.isfinite(fps) or fps <= 0:
        fps = 30.0
    return Run(positions, times, faces, scene, fps, piece_ranges=ranges)
