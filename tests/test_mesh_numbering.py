"""Mesh cloths keep the file's vertex numbering: unreferenced vertices are an error naming them, a UV seam does not
split the cloth, pins index the file's vertices; pins beyond a grid are refused by load_scene."""

from __future__ import annotations

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.cloth import from_mesh
from implicit_cloth.objfile import read_obj
from implicit_cloth.results import cloth_pieces


def _grid(n):
    u = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(u, u)
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def _scene(path, pins=()):
    return {"simulation": {"dt": 0.01, "duration": 0.05},
            "cloth": {"mesh": str(path), "mass": 0.1, "pins": list(pins),
                      "springs": {"structural": {"stiffness": 200.0}, "bend": {"stiffness": 1.0}}},
            "effects": {"gravity": [0.0, 0.0, -9.81]}}


def test_unreferenced_vertices_are_an_error_naming_them(tmp_path):
    v, f = _grid(24)                                          # 576 vertices, all in triangles
    extra = np.full((24, 3), 5.0) + np.arange(24)[:, None]
    verts = np.concatenate([v[:100], extra, v[100:]])         # file vertices 100..123 in no face
    faces = np.where(f >= 100, f + 24, f)
    p = tmp_path / "holes.obj"
    p.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in verts) + "".join(f"f {a + 1} {b + 1} {c + 1}\n"
                                                                            for a, b, c in faces))
    with pytest.raises(ic.SceneError, match=r"cloth\.mesh: vertex 100 is in no triangle \(unreferenced\).*"
                                            r"24 such vertices: 100, 101, 102, 103, 104, \.\.\."):
        ic.Simulator(_scene(p, pins=[100]))


def test_a_uv_seam_does_not_split_the_cloth_and_pins_index_the_file(tmp_path):
    v, f = _grid(8)                                           # 64 vertices
    uv_of_face = np.arange(len(f)) * 3                        # every face corner its own vt: a seam everywhere
    lines = [f"v {a} {b} {c}\n" for a, b, c in v]
    lines += [f"vt {k / 300:.4f} 0.5\n" for k in range(3 * len(f))]
    lines += ["vn 0 0 1\n"]
    lines += [f"f {a + 1}/{t + 1}/1 {b + 1}/{t + 2}/1 {c + 1}/{t + 3}/1\n" for (a, b, c), t in zip(f, uv_of_face)]
    p = tmp_path / "seam.obj"
    p.write_text("".join(lines))
    geo = from_mesh(str(p))
    assert geo.n_vertices == 64
    np.testing.assert_array_equal(geo.positions, v)
    np.testing.assert_array_equal(geo.faces, f)
    assert len(cloth_pieces(geo.faces, 64)) == 1
    sim = ic.Simulator(_scene(p, pins=[7, 42]))
    assert sim.model.n == 64
    traj = sim.run()
    np.testing.assert_array_equal(traj.positions[-1][[7, 42]], v[[7, 42]])     # the file's vertices 8 and 43
    assert np.all(traj.positions[-1][[0, 63], 2] < -1e-4)                      # the others fall


def test_obj_reader_keeps_order_with_negative_indices_and_polygons(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("# a quad and a triangle, relative indices\no sheet\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                 "vt 0 0\ng a\nusemtl x\nf -4/1 -3/1 -2/1 -1/1\nv 2 0 0\nf 2 5 3\n")
    verts, faces = read_obj(p)
    assert verts.shape == (5, 3)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])


def test_grid_pins_out_of_range_are_caught_by_load_scene(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[cloth]\nresolution = [8, 8]\nmass = 0.1\npins = [3, 9999]\n')
    with pytest.raises(ic.SceneError, match=r"^cloth\.pins\[1\]: vertex index out of range \(the cloth has 64 "
                                            r"vertices\), got 9999$"):
        ic.load_scene(p)
    p.write_text('[cloth]\nresolution = [8, 8]\nmass = 0.1\npins = [{vertices = [63, 64]}]\n')
    with pytest.raises(ic.SceneError, match=r"^cloth\.pins\[0\]\.vertices\[1\]: vertex index out of range"):
        ic.load_scene(p)
    p.write_text('[cloth]\nresolution = [8, 8]\nmass = 0.1\npins = [63, "top_left"]\n')
    assert ic.load_scene(p).data["cloth"]["pins"][0]["vertices"] == [63, "top_left"]
