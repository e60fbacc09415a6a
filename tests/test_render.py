"""render with pyvista (VTK's depth buffer): pictures are not blank, an obstacle in front of the cloth hides it and
one behind it is hidden, a cloth draped over a cone hides the cone (the painter's algorithm shows it), keyframed
obstacles are drawn where the collision code has them, movies (GIF, MP4) are written."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from implicit_cloth.cli import main

pytest.importorskip("pyvista")
PIL_Image = pytest.importorskip("PIL.Image")

from implicit_cloth import renderer  # noqa: E402
from implicit_cloth.results import read_run  # noqa: E402


def _grid(n, half, z=None, plane="xy"):
    """An n x n grid's vertices and triangles; ``plane`` "xy" (z from ``z(x, y)``) or "xz" (at y = 0)."""
    u = np.linspace(-half, half, n)
    a, b = np.meshgrid(u, u)
    a, b = a.ravel(), b.ravel()
    if plane == "xy":
        pts = np.stack([a, b, z(a, b) if z is not None else np.zeros_like(a)], 1)
    else:
        pts = np.stack([a, np.zeros_like(a), b + 1.0], 1)
    idx = np.arange(n * n).reshape(n, n)
    p, q, r, s = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return pts, np.concatenate([np.stack([p, q, s], 1), np.stack([p, s, r], 1)])


def _write_run(path, frames, faces, times, obstacles):
    """A run directory as `run` writes it: trajectory.npz and a report with the scene's obstacles."""
    path.mkdir(parents=True, exist_ok=True)
    np.savez(path / "trajectory.npz", positions=np.asarray(frames, float), times=np.asarray(times, float),
             faces=faces)
    scene = {"simulation": {"dt": 0.01, "frame_rate": 10.0}, "cloth": {"kind": "test"}, "obstacles": obstacles}
    (path / "report.json").write_text(json.dumps({"scene": scene}))
    return path


def _sphere(center, **extra):
    return {"shape": "sphere", "radius": 0.2, "center": list(center), "velocity": [0.0, 0.0, 0.0],
            "angular_velocity": [0.0, 0.0, 0.0], "friction": 0.0, **extra}


def _classes(img):
    """Masks of the cloth's blue, the first obstacle's ochre and the white background."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    cloth = (b > r + 25) & (b > g)
    ochre = (r > b + 50) & (g > b + 15)
    background = (r > 245) & (g > 245) & (b > 245)
    return cloth, ochre, background


def _one(run_dir, frame=0, **options):
    run = read_run(run_dir)
    with renderer.scene(run, [frame], labels=False, **options) as sc:
        img = sc.image(0, frame)
        depth = sc.depth()
    return img, depth


# --------------------------------------------------------------------------- occlusion
@pytest.mark.parametrize("side", [-1, 1], ids=["sphere_in_front", "sphere_behind"])
def test_an_obstacle_in_front_hides_the_cloth_and_one_behind_is_hidden(tmp_path, side):
    pts, faces = _grid(21, 0.5, plane="xz")                     # a vertical sheet at y = 0, z from 0.5 to 1.5
    run_dir = _write_run(tmp_path / "r", [pts], faces, [0.0], [_sphere([0.0, 0.35 * side, 1.0])])
    img, depth = _one(run_dir, elev=0.0, azim=-90.0, size=(240, 240))   # camera on -y, looking along +y
    cloth, ochre, background = _classes(img)
    assert cloth.sum() > 0.1 * img.shape[0] * img.shape[1] and background.sum() > 0   # not blank
    h, w = img.shape[:2]
    centre = (slice(h // 2 - 3, h // 2 + 3), slice(w // 2 - 3, w // 2 + 3))
    if side < 0:       # in front: the centre shows the sphere, and it is nearer than the cloth around it
        assert ochre[centre].all() and not cloth[centre].any()
        left = np.flatnonzero(cloth[h // 2])[0] + 2                 # cloth on the centre row, left of the sphere
        assert np.nanmax(depth[centre]) < depth[h // 2, left] - 0.2  # the sphere's front, 0.35 m before the sheet
    else:              # behind: no pixel of the sphere at all (the sheet covers it entirely)
        assert cloth[centre].all() and ochre.sum() == 0


def test_a_cloth_draped_over_a_cone_hides_it_and_the_floor_under_it(tmp_path):
    """Cloth 4 cm above a cone (height 0.4, radius 0.25) and a floor: every cone pixel is hidden. The tip
    poking 6 cm through a lowered cloth is seen, so the test can tell (and the painter's algorithm fails it)."""
    H, R = 0.4, 0.25
    cone = {"shape": "cone", "radius": R, "height": H, "center": [0.0, 0.0, 0.0], "axis": [0.0, 0.0, 1.0],
            "velocity": [0.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 0.0], "friction": 0.0}
    floor = {"shape": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "velocity": [0.0, 0.0, 0.0],
             "angular_velocity": [0.0, 0.0, 0.0], "friction": 0.0}

    def tent(lift):
        return _grid(41, 0.4, z=lambda x, y: np.maximum(H * (1 - np.hypot(x, y) / R), 0.0) + lift)
    draped, faces = tent(0.04)
    poked, _ = tent(0.04)
    poked[:, 2] -= 0.10 * (np.hypot(poked[:, 0], poked[:, 1]) < 0.06)      # a dent at the tip: 6 cm through
    run_dir = _write_run(tmp_path / "r", [draped, poked], faces, [0.0, 0.1], [cone, floor])
    for frame, expect_cone in ((0, False), (1, True)):
        img, depth = _one(run_dir, frame, elev=20.0, azim=-60.0, size=(320, 240), zoom=1.5)
        cloth, ochre, _ = _classes(img)
        assert cloth.sum() > 5000
        if expect_cone:
            assert ochre.sum() > 20
        else:
            assert ochre.sum() == 0


def test_keyframed_obstacle_moves_across_the_picture(tmp_path):
    pts, faces = _grid(5, 0.5, plane="xz")
    keys = [{"time": 0.0, "center": [-0.6, -0.4, 1.0], "rotation": [0.0, 0.0, 0.0]},
            {"time": 1.0, "center": [0.6, -0.4, 1.0], "rotation": [0.0, 0.0, 1.0]}]
    ob = _sphere([-0.6, -0.4, 1.0], keyframes=keys)       # the stored (validated) form: center and velocity too
    run_dir = _write_run(tmp_path / "r", [pts, pts, pts], faces, [0.0, 0.5, 1.0], [ob])
    run = read_run(run_dir)
    cols = []
    with renderer.scene(run, [0, 1, 2], elev=0.0, azim=-90.0, size=(300, 200), labels=False) as sc:
        for k in range(3):
            _, ochre, _ = _classes(sc.image(k, k))
            assert ochre.sum() > 100
            cols.append(np.nonzero(ochre)[1].mean())
    w = 300
    assert cols[0] < 0.4 * w and abs(cols[1] - w / 2) < 0.05 * w and cols[2] > 0.6 * w


# --------------------------------------------------------------------------- command line
def test_render_cli_png_gif_mp4_and_colourings(tmp_path, capsys):
    pts, faces = _grid(9, 0.5, plane="xz")
    frames = [pts + [0.0, 0.05 * k, 0.0] * (pts[:, 2:3] < 1.0) for k in range(5)]
    run_dir = _write_run(tmp_path / "r", frames, faces, [0.0, 0.1, 0.2, 0.3, 0.4], [_sphere([0.0, -0.4, 1.0])])
    assert main(["render", str(run_dir), "--size", "200", "120", "--color", "speed", "--fps", "10"]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err
    with PIL_Image.open(run_dir / "render" / "frames.png") as im:
        assert im.size == (3 * 200, 120)
        a = np.asarray(im.convert("RGB"))
        assert a.std() > 10                                   # not blank
    with PIL_Image.open(run_dir / "render" / "movie.gif") as im:
        assert im.n_frames == 5 and im.info["duration"] == 100
    assert main(["render", str(run_dir), "--size", "160", "120", "--movie", "mp4", "--frames", "-1",
                 "--color", "strain", "--out", str(tmp_path / "mp4")]) == 0
    mp4 = (tmp_path / "mp4" / "movie.mp4").read_bytes()
    assert len(mp4) > 1000 and mp4[4:8] == b"ftyp"
    assert main(["render", str(run_dir), "--color", "rainbow"]) == 2
    assert "--color: must be one of solid, piece, strain, speed, got 'rainbow'" in capsys.readouterr().err
    assert main(["render", str(run_dir), "--backend", "opengl"]) == 2
    assert "--backend: must be one of auto, pyvista, matplotlib, got 'opengl'" in capsys.readouterr().err
    assert main(["render", str(run_dir), "--size", "0", "10"]) == 2
    assert "--size: must be two integers from 16 to 8192" in capsys.readouterr().err
    assert not [p for p in (run_dir / "render").iterdir() if p.name.startswith(".")]


def test_strain_and_speed_per_vertex(tmp_path):
    pts, faces = _grid(3, 0.5, plane="xz")
    stretched = pts.copy()
    stretched[:, 0] *= 1.1                                    # 10 % along x; vertical edges unchanged
    run_dir = _write_run(tmp_path / "r", [pts, stretched], faces, [0.0, 0.5], [])
    run = read_run(run_dir)                                   # no rebuildable cloth in the scene: rest = frame 0
    s = run.strain([0, 1])
    assert np.allclose(s[0], 0.0) and s[1].max() == pytest.approx(0.1, rel=1e-9)
    v = run.speed([1])[0]
    np.testing.assert_allclose(v, np.abs(pts[:, 0]) * 0.1 / 0.5, atol=1e-12)
    assert math.isclose(run.fps, 10.0)
