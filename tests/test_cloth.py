"""Cloth builders: grid conventions, spring topology, masses; triangle meshes via trimesh."""

import numpy as np
import pytest
import trimesh

import implicit_cloth as ic
from implicit_cloth import cloth


def test_grid_conventions_and_spring_counts():
    nx, ny = 5, 4
    g = cloth.grid((2.0, 1.5), (nx, ny), center=(1.0, 2.0, 3.0), plane="xz")
    assert g.positions.shape == (nx * ny, 3)
    # index j*nx + i, i along width (x), j along height (z); top row j = ny-1
    i, j = 3, 2
    assert np.allclose(g.positions[j * nx + i], [1.0 - 1.0 + 3 * 0.5, 2.0, 3.0 - 0.75 + 2 * 0.5])
    assert g.corner("top_left") == (ny - 1) * nx and g.corner("bottom_right") == nx - 1
    assert g.positions[g.corner("top_right"), 2] == pytest.approx(3.75)
    assert len(g.springs["structural"]) == (nx - 1) * ny + nx * (ny - 1)
    assert len(g.springs["shear"]) == 2 * (nx - 1) * (ny - 1)
    assert len(g.springs["bend"]) == (nx - 2) * ny + nx * (ny - 2)
    def L(k):
        return np.linalg.norm(np.diff(g.positions[g.springs[k]], axis=1)[:, 0], axis=1)

    assert set(np.round(L("structural"), 12)) == {0.5}
    assert np.allclose(L("shear"), np.hypot(0.5, 0.5))
    assert set(np.round(L("bend"), 12)) == {1.0}
    assert len(g.faces) == 2 * (nx - 1) * (ny - 1)
    assert cloth.triangle_areas(g.positions, g.faces).sum() == pytest.approx(2.0 * 1.5)
    assert cloth.lumped_areas(g.positions, g.faces).sum() == pytest.approx(2.0 * 1.5)


def test_flat_plane_xy_is_z_up():
    g = cloth.grid((1.0, 1.0), (3, 3), plane="xy")
    assert np.allclose(g.positions[:, 2], 0.0)
    n = np.cross(*(g.positions[g.faces[0, 1:]] - g.positions[g.faces[0, 0]]))
    assert n[2] > 0


def test_grid_mass_spread_equally():
    sim = ic.Simulator({"cloth": {"resolution": [4, 3], "mass": 1.2}})
    assert np.allclose(sim.model.masses, 0.1)
    sim = ic.Simulator({"cloth": {"size": [2.0, 1.0], "resolution": [3, 3], "density": 0.9}})
    assert sim.model.total_mass == pytest.approx(1.8)


def _write_square(tmp_path, fmt):
    g = cloth.grid((1.0, 1.0), (4, 4), plane="xy")
    mesh = trimesh.Trimesh(g.positions, g.faces, process=False)
    path = tmp_path / f"square.{fmt}"
    mesh.export(path)
    return path, g


@pytest.mark.parametrize("fmt", ["obj", "ply", "stl", "off", "glb"])
def test_mesh_cloth_from_file(tmp_path, fmt):
    path, g = _write_square(tmp_path, fmt)
    scene = {"cloth": {"mesh": str(path), "mass": 0.5, "pins": [0],
                       "springs": {"structural": {"stiffness": 100.0}, "bend": {"stiffness": 1.0}}},
             "effects": {"gravity": [0, 0, -9.81]}}
    if fmt == "stl":   # a triangle soup: its shared corners are duplicate vertices, and the user is told so
        with pytest.warns(ic.MeshWarning, match="duplicate vertices"):
            sim = ic.Simulator(scene)
    else:
        sim = ic.Simulator(scene)
    m = sim.model
    assert m.total_mass == pytest.approx(0.5)
    # area-lumped: mass proportional to lumped area
    assert np.allclose(m.masses / m.masses.sum(), m.areas / m.areas.sum())
    # STL stores a triangle soup: every triangle then has its own vertices (no shared edges)
    n_faces = len(m.faces)
    n_edges = len(np.unique(np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]]),
                                    axis=1), axis=0))
    assert m.springs.kinds["structural"].stop == n_edges
    if fmt != "stl":
        assert n_faces == len(g.faces) and m.n == 16
        interior = n_edges - 12   # boundary edges of a 4x4 grid: 4 sides x 3
        assert m.springs.kinds["bend"].stop - m.springs.kinds["bend"].start == interior
    sim.run(duration=0.05)


def test_mesh_bend_springs_join_opposite_vertices():
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    s = cloth.mesh_springs(faces, kinds=("structural", "bend", "shear"))
    assert s["bend"].tolist() == [[0, 3]]
    assert len(s["structural"]) == 5 and len(s["shear"]) == 0


def test_mesh_errors(tmp_path):
    with pytest.raises(ic.SceneError, match=r"cloth\.mesh: file not found"):
        ic.Simulator({"cloth": {"mesh": str(tmp_path / "nope.obj"), "mass": 1.0}})
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ic.SceneError, match=r"cloth\.mesh: mesh has no triangles"):
        ic.Simulator({"cloth": {"mesh": str(bad), "mass": 1.0}})
    with pytest.raises(ic.SceneError, match=r"cloth\.pins\[0\]: corner name 'top_left' only applies to a grid"):
        path, _ = _write_square(tmp_path, "obj")
        ic.Simulator({"cloth": {"mesh": str(path), "mass": 1.0, "pins": ["top_left"]}})
