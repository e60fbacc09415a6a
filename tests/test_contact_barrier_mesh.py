"""The barrier contact method (``collision.method = "barrier"``) against mesh obstacles: a box written as a
triangle mesh, so that the checks here can use the box's closed forms (inside: every coordinate within the
half-extents; the distance from outside: ``|max(|p| - h, 0)|``), independent of the engine's mesh queries.
"""

from __future__ import annotations

import numpy as np
import pytest

import implicit_cloth as ic

trimesh = pytest.importorskip("trimesh")

TH = 0.01
HALF = np.array([0.15, 0.15, 0.1])
CENTER = np.array([0.0, 0.0, -0.15])
G = 9.81


@pytest.fixture(scope="module")
def box_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "box.obj"
    trimesh.creation.box(extents=2 * HALF).export(path)
    return str(path)


def _scene(path, dt=1 / 60, n=24, velocity=(0.0, 0.0, 0.0), friction=0.3):
    return {
        "simulation": {"integrator": "backward_euler", "dt": dt, "duration": 2.0, "frame_rate": 30},
        "cloth": {"size": [0.6, 0.6], "resolution": [n, n], "mass": 0.1, "center": [0.0, 0.0, 0.0], "plane": "xy",
                  "springs": {"structural": {"stiffness": 300.0, "damping": 0.05},
                              "shear": {"stiffness": 30.0, "damping": 0.01},
                              "bend": {"stiffness": 0.5, "damping": 0.001}}},
        "effects": {"gravity": [0.0, 0.0, -G]},
        "obstacles": [{"shape": "mesh", "path": path, "translation": list(CENTER), "velocity": list(velocity),
                       "friction": friction}],
        "collision": {"method": "barrier", "thickness": TH},
    }


def _outside(x, c):
    """Each point's distance from outside the box centred at ``c`` (0 inside) and whether it is inside."""
    p = np.abs(x - c)
    return np.linalg.norm(np.maximum(p - HALF, 0.0), axis=1), np.all(p < HALF, axis=1)


def _energy(sim, s, c):
    """Kinetic + gravity + springs (from their rest lengths) + the barrier's stored energy (IPC's formula on the
    box's distance, its stiffness the vertex's mass over dt^2)."""
    m = sim.model
    ke = 0.5 * float(np.sum(m.masses[:, None] * s.v ** 2))
    grav = float(np.sum(m.masses * G * s.x[:, 2]))
    sp = m.springs
    length = np.linalg.norm(s.x[sp.j] - s.x[sp.i], axis=1)
    g = _outside(s.x, c)[0] - TH / 2
    dh = TH / 2
    on = (g > 0) & (g < dh)
    kappa = m.masses / sim.dt ** 2
    barrier = float(np.sum(kappa[on] * -(g[on] - dh) ** 2 * np.log(g[on] / dh)))
    return ke + grav + 0.5 * float(np.sum(sp.k * (length - sp.L0) ** 2)) + barrier


def test_sheet_on_a_box_mesh_never_inside_energy_never_rises_and_rests(box_path):
    """A 24² sheet dropped on a box mesh, dt 1/60: no vertex inside the box, none nearer than half the thickness,
    the energy never rises, and it comes to rest draped over the box."""
    sim = ic.Simulator(_scene(box_path))
    states = [sim.state]
    for _ in range(120):
        sim.step(1)
        states.append(sim.state)
    for s in states:
        dist, inside = _outside(s.x, CENTER)
        assert not inside.any()
        assert dist.min() > TH / 2
    e = np.array([_energy(sim, s, CENTER) for s in states])
    assert np.all(np.diff(e) <= 1e-6 * abs(e[0]) + 1e-9), np.diff(e).max()
    last = states[-1]
    assert np.sqrt(np.mean(np.sum(last.v ** 2, axis=1))) < 0.05
    assert _outside(last.x, CENTER)[0].min() < TH                 # resting on it, within the barrier's reach
    assert last.x[:, 2].min() < CENTER[2]                         # its sides hang over the box's edges
    assert "energy" not in sim.health.events


@pytest.mark.parametrize("dt", [1 / 60, pytest.param(1 / 30, marks=pytest.mark.slow)])
def test_a_box_mesh_rising_through_a_sheet_lifts_it_never_inside(dt, box_path):
    """A box mesh driven up at 1 m/s into a falling sheet: at every step's end no vertex is inside the box at its
    pose then, and the sheet ends on top of it. (At dt 1/30 a minute: steps of 20 Newton iterations and up to 120
    solves, the line search's halvings each checking the paths against the mesh.)"""
    sim = ic.Simulator(_scene(box_path, dt=dt, velocity=(0.0, 0.0, 1.0), friction=0.0))
    for _ in range(int(round(0.5 / dt))):
        sim.step(1)
        c = CENTER + np.array([0.0, 0.0, 1.0]) * sim.state.t
        dist, inside = _outside(sim.state.x, c)
        assert not inside.any() and dist.min() > TH / 2, sim.state.t
    assert sim.state.x[:, 2].max() > c[2] + HALF[2]
    assert "energy" not in sim.health.events

