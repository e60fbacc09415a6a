"""Headless pictures of a run: a PNG of chosen frames and an animated GIF or MP4, with a progress bar.

Two back-ends. ``pyvista`` (the ``render`` extra; :mod:`implicit_cloth.renderer`) rasterises with VTK's depth
buffer, so contacts are drawn as they are: the surface nearest the camera wins at every pixel; it colours the
cloth by strain, speed or piece. ``matplotlib`` (the fallback when pyvista is missing) draws the cloth's and
the obstacles' triangles in one painter-sorted collection (whole triangles back to front), each shaded by
Lambert's law ``c = base (a + (1 - a) |n . l|)``: wrong exactly where surfaces touch (an obstacle's facets can
show through a cloth lying on it), and ``render`` says so when it falls back.

Obstacles come from the report's scene (``report["scene"]["obstacles"]``, the validated ``[[obstacles]]``
tables): every shape the collision code knows (sphere, box, cone, capsule, plane drawn as a square around the
cloth, mesh), placed at each frame's time by the collision code's own rigid motion, keyframes included
(:mod:`implicit_cloth.results`). Other shapes are skipped with a warning.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from .errors import InputError, SceneError, show
from .export import select_frames
from .export.staging import write_bytes
from .files import atomic_write
from .results import ObstacleWarning, read_run

CLOTH_COLOR = np.array([0.27, 0.51, 0.71])
OBSTACLE_COLOR = np.array([0.75, 0.72, 0.68])
AMBIENT = 0.35
LIGHT = np.array([0.4, -0.5, 0.77]) / np.linalg.norm([0.4, -0.5, 0.77])
MOVIES: tuple[str, ...] = ("gif", "mp4", "none")
BACKENDS: tuple[str, ...] = ("auto", "pyvista", "matplotlib")


class RenderWarning(ObstacleWarning):
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
                 obstacles: Sequence[Any], size: tuple[float, float], dpi: int,
                 elev: float, azim: float, panels: int = 1) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.positions, self.times, self.faces = positions, times, faces
        self.obstacles = list(obstacles)
        self.elev, self.azim = elev, azim
        lo, hi = positions.reshape(-1, 3).min(0), positions.reshape(-1, 3).max(0)
        for ob in self.obstacles:                # bounded obstacles at both ends of the run widen the view
            if ob.shape == "plane":
                continue
            for t in (float(times[0]), float(times[-1])):
                w = ob.world(t)
                lo, hi = np.minimum(lo, w.min(0)), np.maximum(hi, w.max(0))
        self.center = (lo + hi) / 2
        self.half = max(float(np.max(hi - lo)) / 2, 1e-3) * 1.15
        self.fig = Figure(figsize=(size[0] * panels, size[1]), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        self.panels = panels

    def _obstacle_tris(self, t: float) -> list[np.ndarray]:
        return [ob.world(t)[ob.faces] for ob in self.obstacles]

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


def _check_options(movie: str, fps: float, backend: str) -> None:
    if movie not in MOVIES:
        raise InputError(f"--movie: must be one of {', '.join(MOVIES)}, got {show(movie)}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps: must be a finite number > 0, got {show(fps)}")
    if backend not in BACKENDS:
        raise InputError(f"--backend: must be one of {', '.join(BACKENDS)}, got {show(backend)}")


def _check_picture(backend: str, color: str, zoom: float, pixels: Sequence[int]) -> None:
    if backend == "matplotlib" and color != "solid":
        raise InputError(f"--color: the matplotlib back-end draws only solid colour (use --backend pyvista), "
                         f"got {show(color)}")
    if not (isinstance(zoom, (int, float)) and math.isfinite(zoom) and zoom > 0):
        raise InputError(f"--zoom: must be a finite number > 0, got {show(zoom)}")
    if len(pixels) != 2 or any(not isinstance(p, int) or p < 16 or p > 8192 for p in pixels):
        raise InputError(f"--size: must be two integers from 16 to 8192 (width height, pixels), got {list(pixels)}")


def _pick_backend(backend: str) -> str:
    if backend != "auto":
        return backend
    try:
        import pyvista  # noqa: F401
    except ImportError:
        warnings.warn("pyvista is not installed (pip install 'implicit_cloth[render]'): drawing with matplotlib, "
                      "whose painter's algorithm sorts whole triangles, so at contacts an obstacle may show "
                      "through the cloth", RenderWarning, stacklevel=3)
        return "matplotlib"
    return "pyvista"


def render_run(run_dir: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
               frames: Sequence[int] | None = None, movie: str = "gif", fps: float = 15.0,
               max_movie_frames: int = 120, size: tuple[float, float] = (4.0, 4.0), dpi: int = 80,
               elev: float = 20.0, azim: float = -60.0, backend: str = "auto", color: str = "solid",
               pixels: tuple[int, int] = (640, 480), zoom: float = 1.0, progress: bool = False) -> list[Path]:
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
        ``gif`` via Pillow; ``mp4`` via imageio-ffmpeg (the render extra) or ``ffmpeg`` on the PATH.
    fps : float
        Movie frames per second (of wall-clock playback).
    max_movie_frames : int
        The movie uses at most this many frames, evenly spaced (always the first and last).
    backend : {"auto", "pyvista", "matplotlib"}
        ``pyvista`` (:mod:`implicit_cloth.renderer`): a z-buffer, right at contacts. ``matplotlib``: the
        painter's algorithm (whole triangles back to front), which is wrong where surfaces touch; ``auto``
        takes pyvista when it is installed and warns when it falls back.
    color : {"solid", "piece", "strain", "speed"}
        The cloth's colouring (pyvista only).
    pixels : (width, height)
        Size of each picture in pixels (pyvista).
    size, dpi : figure size per panel in inches, and resolution (matplotlib).
    elev, azim : camera elevation and azimuth, degrees.
    zoom : float
        The camera this many times closer than the framing of the whole run (pyvista).
    progress : bool
        A progress bar over the movie's frames on stderr.

    Returns
    -------
    list of Path
        Files written, each atomically.
    """
    _check_options(movie, fps, backend)
    _check_picture(backend, color, zoom, pixels)
    run_dir = Path(run_dir)
    run = read_run(run_dir)
    n = run.n_frames
    chosen = select_frames(n, frames if frames is not None else sorted({0, (n - 1) // 2, n - 1}))
    m = min(n, max(int(max_movie_frames), 2))
    movie_frames = [int(f) for f in np.unique(np.rint(np.linspace(0, n - 1, m)).astype(int))]
    if movie == "mp4":
        _mp4_writer_available()
    out = Path(out) if out is not None else run_dir / "render"
    out.mkdir(parents=True, exist_ok=True)
    if _pick_backend(backend) == "matplotlib":
        return _render_matplotlib(run_dir, run, out, chosen, movie, movie_frames, fps, size, dpi, elev, azim,
                                  progress)
    return _render_pyvista(run, out, chosen, movie, movie_frames, fps, progress,
                           {"color": color, "size": (int(pixels[0]), int(pixels[1])), "elev": elev, "azim": azim,
                            "zoom": zoom})


def _render_pyvista(run: Any, out: Path, chosen: list[int], movie: str, movie_frames: list[int], fps: float,
                    progress: bool, opts: dict[str, Any]) -> list[Path]:
    """frames.png and the movie from one depth-buffered scene (one colour scale for both)."""
    from . import renderer

    renderer.check_coloring(opts["color"])
    every = sorted(set(chosen) | (set(movie_frames) if movie != "none" else set()))
    place = {f: k for k, f in enumerate(every)}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run.obstacles()
    for w in caught:
        warnings.warn(str(w.message), RenderWarning, stacklevel=3)
    with renderer.scene(run, every, **opts) as sc:
        written = [_save_png(out / "frames.png", np.concatenate([sc.image(place[f], f) for f in chosen], axis=1))]
        if movie == "none":
            return written
        bar = _progress(len(movie_frames), progress)
        try:
            def pictures() -> Iterator[np.ndarray]:
                for f in movie_frames:
                    yield sc.image(place[f], f)
                    if bar is not None:
                        bar.update(1)
            written.append(_save_movie(out, movie, pictures(), fps))
        finally:
            if bar is not None:
                bar.close()
    return written


def _progress(total: int, show: bool) -> Any:
    if not show:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="frame", desc="render", leave=False)


def _save_png(path: Path, rgb: np.ndarray) -> Path:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return write_bytes(path, buf.getvalue())


def _mp4_writer_available() -> None:
    try:
        import imageio_ffmpeg  # noqa: F401
        return
    except ImportError:
        pass
    if shutil.which("ffmpeg") is None:
        raise InputError("--movie: mp4 needs imageio-ffmpeg (pip install 'implicit_cloth[render]') or ffmpeg on "
                         "the PATH (or use --movie gif), got 'mp4'")


def _save_movie(out: Path, movie: str, pictures: Any, fps: float) -> Path:
    """``movie.gif`` (Pillow) or ``movie.mp4`` (H.264 through imageio-ffmpeg or the PATH's ffmpeg)."""
    if movie == "gif":
        from PIL import Image

        images = [Image.fromarray(p).quantize(colors=255) for p in pictures]
        duration = max(int(round(1000.0 / fps)), 20)

        def save(fh: Any) -> None:
            images[0].save(fh, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
        return atomic_write(out / "movie.gif", save)
    target = out / "movie.mp4"
    tmp = out / f".movie.{os.getpid()}.tmp.mp4"
    try:
        try:
            import imageio_ffmpeg
            exe = imageio_ffmpeg.get_ffmpeg_exe()
        except ImportError:
            exe = shutil.which("ffmpeg") or "ffmpeg"
        _ffmpeg_encode(exe, pictures, tmp, fps)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    return target


def _ffmpeg_encode(exe: str, pictures: Any, path: Path, fps: float) -> None:
    import subprocess

    proc = None
    try:
        for p in pictures:
            h, w = p.shape[:2]
            if proc is None:
                proc = subprocess.Popen([exe, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
                                         "-s", f"{w}x{h}", "-r", f"{fps:g}", "-i", "-", "-vf",
                                         "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264", "-pix_fmt",
                                         "yuv420p", "-movflags", "+faststart", str(path)],
                                        stdin=subprocess.PIPE, stderr=subprocess.PIPE)
            assert proc.stdin is not None
            proc.stdin.write(np.ascontiguousarray(p).tobytes())
    finally:
        if proc is not None:
            _, err = proc.communicate()          # closes stdin (the end of the video) and reads the errors
            if proc.returncode != 0:
                why = " ".join(err.decode(errors="replace").split())[:200]
                raise OSError(f"ffmpeg could not write {path.name} ({why})")


def _render_matplotlib(run_dir: Path, run: Any, out: Path, chosen: list[int], movie: str,
                       movie_frames: list[int], fps: float, size: tuple[float, float], dpi: int, elev: float,
                       azim: float, progress: bool) -> list[Path]:
    """The painter's-algorithm fallback (see :class:`_Renderer`)."""
    positions, times, faces = run.positions, run.times, run.faces
    obstacles = run.obstacles()
    written: list[Path] = []
    still = _Renderer(positions, times, faces, obstacles, size, dpi, elev, azim, panels=len(chosen))
    still.draw(chosen)
    buf = io.BytesIO()
    still.fig.savefig(buf, format="png")
    written.append(write_bytes(out / "frames.png", buf.getvalue()))
    if movie == "none":
        return written
    r = _Renderer(positions, times, faces, obstacles, size, dpi, elev, azim)

    bar = _progress(len(movie_frames), progress)

    def pictures() -> Iterator[np.ndarray]:
        for f in movie_frames:
            r.draw([int(f)])
            yield np.asarray(r.rgba())[..., :3].copy()
            if bar is not None:
                bar.update(1)
    try:
        written.append(_save_movie(out, movie, pictures(), fps))
    finally:
        if bar is not None:
            bar.close()
    return written
