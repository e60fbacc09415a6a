"""Headless pictures of a run: a PNG of chosen frames and an animated GIF (or MP4 with ffmpeg).

Drawn with matplotlib's Agg canvas (no display, no pyplot state): the cloth's
triangles and the obstacles' surfaces in one painter-sorted collection,
each triangle shaded by Lambert's law ``c = base (a + (1 - a) |n . l|)``
(two-sided, ambient ``a``) for a light direction ``l`` fixed to the scene.
Needs the ``render`` extra (matplotlib, Pillow).

Obstacles come from the report's scene (``report["scene"]["obstacles"]``, the
``[[obstacles]]`` tables of a scene): every shape the collision code knows
(sphere, box, cone, capsule, plane drawn as a square the size of the scene,
mesh), validated and placed at each frame's time by the collision code's own
rigid motion. Other shapes are skipped with a warning.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .errors import InputError, SceneError, show
from .export import load_run, select_frames
from .files import atomic_write

CLOTH_COLOR = np.array([0.27, 0.51, 0.71])
OBSTACLE_COLOR = np.array([0.75, 0.72, 0.68])
AMBIENT = 0.35
LIGHT = np.array([0.4, -0.5, 0.77]) / np.linalg.norm([0.4, -0.5, 0.77])
MOVIES: tuple[str, ...] = ("gif", "mp4", "none")


class RenderWarning(UserWarning):
    """Something of the scene could not be drawn (an unknown obstacle shape); the picture is made without it."""


# --------------------------------------------------------------------------- obstacles as triangles
def _local_triangles(spec: Mapping[str, Any]) -> np.ndarray:
    """Triangles ``(T, 3, 3)`` of a validated obstacle in its local frame (as the collision shapes define it)."""
    import trimesh

    shape = spec["shape"]
    if shape == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=float(spec["radius"]))
    elif shape == "box":
        m = trimesh.creation.box(extents=spec["size"])
    elif shape == "cone":
        m = trimesh.creation.cone(radius=float(spec["radius"]), height=float(spec["height"]), sections=24)
    elif shape == "capsule":
        m = trimesh.creation.capsule(height=float(spec["height"]), radius=float(spec["radius"]), count=[16, 16])
    else:   # mesh
        from .geometry import load_obstacle_mesh

        verts, faces = load_obstacle_mesh(spec["path"])
        return np.asarray(verts, float)[faces] * float(spec["scale"])
    return np.asarray(m.vertices, float)[np.asarray(m.faces)]


def obstacle_triangles(obstacle: Mapping[str, Any], t: float, extent: tuple[np.ndarray, float]
                       ) -> np.ndarray | None:
    """Triangles ``(T, 3, 3)`` (m) of one obstacle at time ``t``; None (with a warning) if it cannot be drawn.

    The table is validated as a scene's ``[[obstacles]]`` entry and placed by the collision code's own rigid
    motion (:func:`implicit_cloth.collision.shapes.placement`: velocity, angular velocity or keyframes), so the
    picture shows the obstacle where the simulation had it. ``extent`` = (centre, half-size) of the scene, used
    for the size and place of a plane's square.
    """
    from .collision.shapes import placement
    from .config.registry import OBSTACLE_SHAPES
    from .obstacles import validate_obstacles

    shape = obstacle.get("shape")
    if shape not in OBSTACLE_SHAPES:
        warnings.warn(f"obstacles: shape {shape!r} is not drawn (drawn: {', '.join(OBSTACLE_SHAPES)})",
                      RenderWarning, stacklevel=3)
        return None
    try:
        spec = validate_obstacles([obstacle])[0]
        motion = placement(spec)
        if shape == "plane":
            c, half = extent
            q = motion.to_local(np.asarray(c, float)[None], t)[0]          # the scene centre, on the plane
            sq = np.array([[q[0] + sa * half, q[1] + sb * half, 0.0]
                           for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            local = sq[[[0, 1, 2], [0, 2, 3]]]
        else:
            local = _local_triangles(spec)
    except (SceneError, KeyError, TypeError, ValueError, OSError) as exc:
        warnings.warn(f"obstacles: a {shape!r} obstacle is not drawn ({type(exc).__name__}: {exc})",
                      RenderWarning, stacklevel=3)
        return None
    return motion.to_world(local.reshape(-1, 3), t).reshape(local.shape)


# --------------------------------------------------------------------------- drawing
def _shade(tris: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Lambert shading of each triangle, two-sided: ``base (a + (1 - a) |n . l|)``, RGB in [0, 1]."""
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    lam = np.abs(n @ LIGHT)
    return np.clip(base[None, :] * (AMBIENT + (1 - AMBIENT) * lam)[:, None], 0, 1)


class _Renderer:
    """Draws frames of one run on one Agg figure."""

    def __init__(self, positions: np.ndarray, times: np.ndarray, faces: np.ndarray,
                 obstacles: Sequence[Mapping[str, Any]], size: tuple[float, float], dpi: int,
                 elev: float, azim: float, panels: int = 1) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.positions, self.times, self.faces = positions, times, faces
        self.obstacles = list(obstacles)
        self.elev, self.azim = elev, azim
        lo, hi = positions.reshape(-1, 3).min(0), positions.reshape(-1, 3).max(0)
        with warnings.catch_warnings():          # bounded obstacles at both ends of the run widen the view
            warnings.simplefilter("ignore")
            for ob in self.obstacles:
                if ob.get("shape") == "plane":
                    continue
                for t in (float(times[0]), float(times[-1])):
                    tri = obstacle_triangles(ob, t, ((lo + hi) / 2, 1.0))
                    if tri is not None and len(tri):
                        lo, hi = np.minimum(lo, tri.reshape(-1, 3).min(0)), np.maximum(hi, tri.reshape(-1, 3).max(0))
        self.center = (lo + hi) / 2
        self.half = max(float(np.max(hi - lo)) / 2, 1e-3) * 1.15
        self.fig = Figure(figsize=(size[0] * panels, size[1]), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        self.panels = panels
        self._warned = False

    def _obstacle_tris(self, t: float) -> list[np.ndarray]:
        out = []
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for ob in self.obstacles:
                tri = obstacle_triangles(ob, t, (self.center, self.half))
                if tri is not None:
                    out.append(tri)
        if not self._warned:          # each warning once per picture, not once per frame
            for w in caught:
                warnings.warn(str(w.message), RenderWarning, stacklevel=4)
            self._warned = True
        return out

    def draw(self, frames: Sequence[int]) -> None:
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.fig.clear()
        for k, f in enumerate(frames):
            ax = self.fig.add_subplot(1, len(frames), k + 1, projection="3d")
            cloth = self.positions[f][self.faces]
            tris = [cloth]
            colors = [_shade(cloth, CLOTH_COLOR)]
            for ob in self._obstacle_tris(float(self.times[f])):
                tris.append(ob)
                colors.append(_shade(ob, OBSTACLE_COLOR))
            shade = np.concatenate(colors)
            coll = Poly3DCollection(np.concatenate(tris), facecolors=shade,
                                    edgecolors=shade, linewidths=0.3)   # edges in the face colour: no seams
            ax.add_collection3d(coll)
            c, h = self.center, self.half
            ax.set_xlim(c[0] - h, c[0] + h)
            ax.set_ylim(c[1] - h, c[1] + h)
            ax.set_zlim(c[2] - h, c[2] + h)
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=self.elev, azim=self.azim)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            ax.set_zlabel("z (m)")
            ax.set_title(f"frame {f}, t = {self.times[f]:.3g} s", fontsize=9)
        self.fig.tight_layout()
        self.canvas.draw()

    def rgba(self) -> np.ndarray:
        return np.asarray(self.canvas.buffer_rgba()).copy()


def _report_obstacles(run_dir: Path) -> list[Mapping[str, Any]]:
    p = run_dir / "report.json"
    try:
        report = json.loads(p.read_text())
    except (OSError, ValueError):
        return []
    scene = report.get("scene") or {}
    obs = scene.get("obstacles", []) if isinstance(scene, Mapping) else []
    return [o for o in obs if isinstance(o, Mapping)] if isinstance(obs, list) else []


def render_run(run_dir: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
               frames: Sequence[int] | None = None, movie: str = "gif", fps: float = 15.0,
               max_movie_frames: int = 120, size: tuple[float, float] = (4.0, 4.0), dpi: int = 80,
               elev: float = 20.0, azim: float = -60.0) -> list[Path]:
    """Draw a run: ``frames.png`` (the chosen frames side by side) and ``movie.gif`` / ``movie.mp4``.

    Parameters
    ----------
    run_dir : path
        Directory with ``trajectory.npz`` (and ``report.json`` for the obstacles).
    out : path, optional
        Output directory (default ``RUN_DIR/render``).
    frames : list of int, optional
        Frames of the PNG (negative from the end); default first, middle, last.
    movie : {"gif", "mp4", "none"}
        ``gif`` via Pillow; ``mp4`` needs ``ffmpeg`` on the PATH.
    fps : float
        Movie frames per second (of wall-clock playback).
    max_movie_frames : int
        The movie uses at most this many frames, evenly spaced (always the first and last).
    size, dpi : figure size per panel in inches, and resolution.
    elev, azim : camera elevation and azimuth, degrees.

    Returns
    -------
    list of Path
        Files written, each atomically.
    """
    if movie not in MOVIES:
        raise InputError(f"--movie: must be one of {', '.join(MOVIES)}, got {show(movie)}")
    if movie == "mp4" and shutil.which("ffmpeg") is None:
        raise InputError("--movie: mp4 needs ffmpeg on the PATH (use --movie gif), got 'mp4'")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps: must be a finite number > 0, got {show(fps)}")
    run_dir = Path(run_dir)
    positions, times, faces = load_run(run_dir)
    n = len(positions)
    chosen = select_frames(n, frames if frames is not None else sorted({0, (n - 1) // 2, n - 1}))
    obstacles = _report_obstacles(run_dir)
    out = Path(out) if out is not None else run_dir / "render"
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []

    still = _Renderer(positions, times, faces, obstacles, size, dpi, elev, azim, panels=len(chosen))
    still.draw(chosen)
    buf = io.BytesIO()
    still.fig.savefig(buf, format="png")
    written.append(atomic_write(out / "frames.png", lambda f: f.write(buf.getvalue())))

    if movie == "none":
        return written
    m = min(n, max(int(max_movie_frames), 2))
    movie_frames = np.unique(np.rint(np.linspace(0, n - 1, m)).astype(int))
    r = _Renderer(positions, times, faces, obstacles, size, dpi, elev, azim)
    r._warned = True                          # the still picture has warned already
    if movie == "gif":
        from PIL import Image

        images = []
        for f in movie_frames:
            r.draw([int(f)])
            images.append(Image.fromarray(r.rgba()).convert("RGB").quantize(colors=255))
        duration = max(int(round(1000.0 / fps)), 20)

        def save(fh: Any) -> None:
            images[0].save(fh, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)

        written.append(atomic_write(out / "movie.gif", save))
    else:
        from matplotlib.animation import FFMpegWriter

        target = out / "movie.mp4"
        tmp = out / f".movie.mp4.{os.getpid()}.tmp.mp4"
        try:
            writer = FFMpegWriter(fps=fps)  # type: ignore[arg-type]  # a float rate works; the stubs say int
            with writer.saving(r.fig, str(tmp), dpi):
                for f in movie_frames:
                    r.draw([int(f)])
                    writer.grab_frame()
            os.replace(tmp, target)
        finally:
            if tmp.exists():
                tmp.unlink()
        written.append(target)
    return written
