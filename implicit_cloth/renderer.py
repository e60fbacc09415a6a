"""Depth-buffered pictures of a run with pyvista (VTK), off-screen: the ``render`` extra's default back-end.

VTK rasterises every triangle with a z-buffer, so at a contact each pixel shows the surface nearest the camera:
a cloth resting on a cone hides the tip it lies on, a floor under the cloth is hidden by it. Headless machines
render through EGL or OSMesa (Mesa's software OpenGL); no display is needed.

The cloth is coloured ``solid``, by ``piece`` (connected component), by ``strain`` (per vertex, the largest
``l / L - 1`` of its edges, against the rest shape) or by ``speed`` (m/s, central differences of the kept
frames), with one colour range for the whole picture or movie and a colour bar. Every obstacle of the run's
scene is drawn with its own colour at its pose at each frame's time, from the collision code's own motion
(:mod:`implicit_cloth.results`), keyframed ones included. The camera looks at the centre of the cloth's motion
from elevation ``elev`` and azimuth ``azim`` (degrees, z up: azimuth 0 looks along -x, -90 along +y), framed to
hold the cloth and the bounded obstacles over the run, ``zoom`` times closer.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Iterator, Sequence

import numpy as np

from .errors import InputError
from .errors import show as _fmt
from .results import Run, vertex_normals

COLORINGS: tuple[str, ...] = ("solid", "piece", "strain", "speed")
CLOTH_COLOR = (0.27, 0.51, 0.71)
PIECE_COLORS = ((0.27, 0.51, 0.71), (0.84, 0.37, 0.30), (0.36, 0.64, 0.35), (0.58, 0.40, 0.74),
                (0.90, 0.62, 0.20), (0.30, 0.70, 0.75), (0.85, 0.45, 0.65), (0.55, 0.55, 0.25))
#: obstacle colours, in the scene's order (warm and neutral tones, none of them the cloth's blue)
OBSTACLE_COLORS = ((0.85, 0.65, 0.30), (0.80, 0.78, 0.74), (0.70, 0.42, 0.30), (0.55, 0.62, 0.45),
                   (0.62, 0.52, 0.66), (0.75, 0.60, 0.55))
PLANE_COLOR = (0.80, 0.78, 0.74)
BACKGROUND = (1.0, 1.0, 1.0)
VIEW_ANGLE = 30.0     # degrees


def _camera_direction(elev: float, azim: float) -> np.ndarray:
    e, a = math.radians(elev), math.radians(azim)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def _bounds(run: Run, frames: Sequence[int]) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere around the cloth over the run and the bounded obstacles at the frames."""
    pts = [run.positions.reshape(-1, 3)]
    for ob in run.obstacles():
        if ob.shape != "plane":
            pts.extend(ob.world(run.times[f]) for f in sorted({frames[0], frames[len(frames) // 2], frames[-1]}))
    allp = np.concatenate(pts)
    lo, hi = allp.min(0), allp.max(0)
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)


def _matrix(c: np.ndarray, R: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, c
    return m


def _scalars(run: Run, frames: list[int], color: str) -> tuple[np.ndarray | None, str, str]:
    if color == "strain":
        return np.maximum(run.strain(frames), 0.0), "stretch (l / L - 1)", "viridis"
    if color == "speed":
        return run.speed(frames), "speed (m/s)", "viridis"
    return None, "", ""


def _clim(values: np.ndarray) -> tuple[float, float]:
    """From 0 to the largest value over all the frames drawn: one scale for the whole picture or movie."""
    return 0.0, max(float(values.max()), 1e-6)


class _Scene:
    """One off-screen plotter holding the cloth and the obstacles, updated in place frame after frame."""

    def __init__(self, run: Run, frames: list[int], color: str, size: tuple[int, int], elev: float, azim: float,
                 zoom: float, labels: bool) -> None:
        import pyvista

        pv: Any = pyvista           # pyvista's own annotations are stricter than its behaviour (colour map names)

        self.pv, self.run, self.labels = pv, run, labels
        self.values, title, cmap = _scalars(run, frames, color)
        self.plotter: Any = pv.Plotter(off_screen=True, window_size=list(size))
        self.plotter.set_background(BACKGROUND)
        cells = np.hstack([np.full((len(run.faces), 1), 3), run.faces]).ravel()
        self.cloth = pv.PolyData(run.positions[frames[0]].copy(), cells)
        kw: dict[str, Any] = {"smooth_shading": False, "specular": 0.15, "ambient": 0.15, "diffuse": 0.85}
        if self.values is not None:
            self.cloth.point_data["value"] = self.values[0]
            actor = self.plotter.add_mesh(self.cloth, scalars="value", cmap=cmap, clim=_clim(self.values),
                                  scalar_bar_args={"title": title, "color": "black", "vertical": True,
                                                   "position_x": 0.86, "position_y": 0.15, "height": 0.7,
                                                   "width": 0.06, "title_font_size": 12, "label_font_size": 11},
                                  **kw)
        elif color == "piece":
            rgb = np.zeros((run.positions.shape[1], 3))
            for k, verts in enumerate(run.pieces()):
                rgb[verts] = PIECE_COLORS[k % len(PIECE_COLORS)]
            self.cloth.point_data["rgb"] = (rgb * 255).astype(np.uint8)
            actor = self.plotter.add_mesh(self.cloth, scalars="rgb", rgb=True, **kw)
        else:
            actor = self.plotter.add_mesh(self.cloth, color=CLOTH_COLOR, **kw)
        actor.prop.interpolation = "gouraud"      # shaded with the vertex normals set at every frame
        self.obstacles = []
        for k, ob in enumerate(run.obstacles()):
            mesh = pv.PolyData(ob.vertices, np.hstack([np.full((len(ob.faces), 1), 3), ob.faces]).ravel())
            col = PLANE_COLOR if ob.shape == "plane" else OBSTACLE_COLORS[k % len(OBSTACLE_COLORS)]
            actor = self.plotter.add_mesh(mesh, color=col, smooth_shading=ob.shape in ("sphere", "capsule"),
                                          specular=0.2, ambient=0.15, diffuse=0.85)
            self.obstacles.append((ob, actor))
        center, radius = _bounds(run, frames)
        distance = radius / math.sin(math.radians(VIEW_ANGLE) / 2) / max(zoom, 1e-3)
        self.label = None
        if labels:      # one corner annotation, its text changed per frame (adding actors re-renders)
            self.label = self.plotter.add_text(" ", position="upper_left", font_size=10, color="black")
        cam = self.plotter.camera
        cam.focal_point = tuple(center)
        cam.position = tuple(center + distance * _camera_direction(elev, azim))
        cam.up = (0.0, 0.0, 1.0)
        cam.view_angle = VIEW_ANGLE

    def image(self, index: int, frame: int) -> np.ndarray:
        """The RGB picture (H, W, 3) uint8 of ``frame`` (``index``: its place in the frames given)."""
        run = self.run
        x = run.positions[frame]
        self.cloth.points = x
        self.cloth.point_data["Normals"] = vertex_normals(x, run.faces)
        self.cloth.point_data.active_normals_name = "Normals"
        if self.values is not None:
            self.cloth.point_data["value"] = self.values[index]
        t = float(run.times[frame])
        for ob, actor in self.obstacles:
            actor.user_matrix = _matrix(*ob.pose(t))
        if self.label is not None:
            self.label.SetText(2, f"frame {frame}, t = {t:.3g} s")      # 2: the upper left corner
        self.plotter.renderer.ResetCameraClippingRange()
        self.plotter.render()
        return np.asarray(self.plotter.screenshot(return_img=True))[..., :3].copy()

    def depth(self) -> np.ndarray:
        """The z-buffer of the last picture (H, W) as distances along the view direction, m (pyvista gives
        camera-space z, negative in front of the camera); NaN where nothing was drawn."""
        return -np.asarray(self.plotter.get_image_depth(fill_value=np.nan), float)

    def close(self) -> None:
        self.plotter.close()


def check_coloring(color: str) -> str:
    if color not in COLORINGS:
        raise InputError(f"--color: must be one of {', '.join(COLORINGS)}, got {_fmt(color)}")
    return color


@contextlib.contextmanager
def scene(run: Run, frames: list[int], color: str = "solid", size: tuple[int, int] = (640, 480),
          elev: float = 20.0, azim: float = -60.0, zoom: float = 1.0, labels: bool = True) -> Iterator[_Scene]:
    """An off-screen picture maker for ``frames`` of ``run`` (``.image(i, frame)``, ``.depth()``), closed after."""
    import pyvista as pv

    check_coloring(color)
    with contextlib.suppress(Exception):
        pv.vtk_verbosity("off")              # no "bad X server connection" chatter on headless machines
    s = _Scene(run, list(frames), color, size, elev, azim, zoom, labels)
    try:
        yield s
    finally:
        s.close()


def images(run: Run, frames: Sequence[int], progress: bool = False, **options: Any) -> Iterator[np.ndarray]:
    """RGB pictures (H, W, 3) uint8 of ``frames``, one after the other (a tqdm bar on stderr with ``progress``)."""
    frames = list(frames)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(frames), unit="frame", desc="render", leave=False)
    try:
        with scene(run, frames, **options) as s:
            for k, f in enumerate(frames):
                yield s.image(k, f)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
