"""Property tests (hypothesis): what any scene, valid or not, can do.

* A random valid scene (grid 2..6 x 2..6, 1..25 steps, any integrator, stiffness up to 1e5 N/m, masses down to
  1e-2 kg, dt up to 0.05 s, so that explicit runs often diverge) either runs to the end with a finite trajectory,
  finite energies and status "ok", or raises ic.DivergenceError (documented) whose partial trajectory is finite.
  Never another exception, never a NaN in a returned trajectory. (Outside these ranges: see
  test_extreme_stiffness_to_mass_ratio below.)
* A random invalid scene (one mutation of a valid one: a bad value of the wrong type, range, length or
  finiteness at any key; an unknown key in any table; a table replaced by a value; a missing required key; a
  conflicting key; a scene that is not a table) raises ic.SceneError, one line, starting with the dotted path of
  the mutated key (or its table), from Simulator(scene); never another exception type.

Settings (counts chosen so that this file runs in well under 40 s on a shared 2-core machine):
valid scenes max_examples=300, invalid scenes max_examples=800, both deadline=None; derandomize=True so that a
CI run and a local run try the same examples.
"""

from __future__ import annotations

import copy
import datetime
import math
import string
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import implicit_cloth as ic
from implicit_cloth import config
from implicit_cloth import scene as sc

SETTINGS_VALID = settings(max_examples=300, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
SETTINGS_INVALID = settings(max_examples=800, deadline=None, derandomize=True,
                            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

INF, NAN = float("inf"), float("nan")


def log_uniform(lo_exp: float, hi_exp: float):
    return st.floats(lo_exp, hi_exp).map(lambda e: float(10.0 ** e))


def vec(n: int, lim: float):
    return st.lists(st.floats(-lim, lim, allow_nan=False), min_size=n, max_size=n)


# --------------------------------------------------------------------------- valid scenes
@st.composite
def valid_scenes(draw):
    integrator = draw(st.sampled_from(ic.INTEGRATORS))
    nx, ny = draw(st.integers(2, 6)), draw(st.integers(2, 6))
    simulation = _simulation(draw, integrator)
    cloth = _cloth(draw, nx, ny)
    effects = _effects(draw)
    scene = {"cloth": cloth}
    if draw(st.booleans()) or effects:
        scene["effects"] = effects
    if draw(st.booleans()) or integrator != "backward_euler":
        scene["simulation"] = simulation
    if draw(st.booleans()):
        scene["solver"] = {"tolerance": draw(log_uniform(-8, -1)),
                           "max_iterations": draw(st.integers(1, 1000)),
                           "preconditioner": draw(st.sampled_from(config.PRECONDITIONERS.names()))}
    return scene


def _simulation(draw, integrator):
    dt = draw(log_uniform(-3, -1.3))                      # 1 ms .. 50 ms
    simulation = {"integrator": integrator, "dt": dt, "duration": draw(st.integers(1, 25)) * dt,
                  "frame_rate": draw(st.sampled_from([5.0, 30.0, 60.0, 1000.0]))}
    if draw(st.booleans()):
        simulation["divergence_factor"] = draw(log_uniform(0, 6))
    if draw(st.booleans()):
        adaptive = {"enabled": draw(st.booleans()), "max_halvings": draw(st.integers(0, 6)),
                    "grow_after": draw(st.integers(1, 6)), "max_strain": draw(log_uniform(-2, 1)),
                    "max_energy_growth": draw(st.floats(0.0, 10.0)), "retry_unconverged": draw(st.booleans())}
        simulation["adaptive"] = {k: v for k, v in adaptive.items() if draw(st.booleans())}
    if draw(st.booleans()):
        simulation["strain_limit"] = {"max_strain": draw(log_uniform(-2, 0))}
        if draw(st.booleans()):
            simulation["strain_limit"]["iterations"] = draw(st.integers(1, 50))
    return simulation


def _cloth(draw, nx, ny):
    cloth = {}
    if draw(st.booleans()):
        cloth["size"] = [draw(log_uniform(-1, 0.7)), draw(log_uniform(-1, 0.7))]
    cloth["resolution"] = [nx, ny]
    if draw(st.booleans()):
        cloth["center"] = draw(vec(3, 5.0))
    if draw(st.booleans()):
        cloth["plane"] = draw(st.sampled_from(sc.PLANES))
    how = draw(st.sampled_from(["mass", "density", "material", "material+mass"]))
    if "material" in how:
        cloth["material"] = draw(st.sampled_from(sorted(ic.MATERIALS)))
    if "mass" in how:
        cloth["mass"] = draw(log_uniform(-2, 1))
    elif how == "density":
        cloth["density"] = draw(log_uniform(-2, 0.5))
    if draw(st.booleans()):
        cloth["velocity"] = draw(vec(3, 2.0))
    springs = {}
    for kind in sc.SPRING_KINDS:
        if draw(st.booleans()):
            spec = {}
            if "material" not in cloth or draw(st.booleans()):
                spec["stiffness"] = draw(st.one_of(st.just(0.0), log_uniform(0, 5)))
            if draw(st.booleans()):
                spec["damping"] = draw(st.one_of(st.just(0.0), log_uniform(-3, 0)))
            springs[kind] = spec
    if springs or draw(st.booleans()):
        cloth["springs"] = springs
    n = nx * ny
    vertex = st.one_of(st.sampled_from(sc.CORNERS), st.integers(0, n - 1))
    pins = draw(st.lists(vertex, max_size=3))
    if draw(st.booleans()):
        pins.append({"vertices": draw(st.lists(vertex, min_size=1, max_size=2)), "velocity": draw(vec(3, 0.5))})
    if pins or draw(st.booleans()):
        cloth["pins"] = _pins_apart(pins, nx, ny)
    return cloth


def _pins_apart(pins, nx, ny):
    """The same vertex in a moving group and as a fixed pin would be a (tested) error: keep the groups apart."""
    fixed = {p for p in pins if not isinstance(p, dict)}
    for p in pins:
        if isinstance(p, dict):
            p["vertices"] = [v for v in p["vertices"] if v not in fixed and _index(v, nx, ny) not in
                             {_index(f, nx, ny) for f in fixed}] or None
    return [p for p in pins if not (isinstance(p, dict) and p["vertices"] is None)]


def _effects(draw):
    effects = {}
    if draw(st.booleans()):
        effects["gravity"] = draw(st.one_of(st.just([0.0, 0.0, -9.81]), vec(3, 20.0)))
    if draw(st.booleans()):
        effects["drag"] = draw(st.floats(0.0, 2.0))
        if draw(st.booleans()):
            effects["wind"] = {"velocity": draw(vec(3, 5.0))}
    return effects


def _index(v, nx, ny):
    if isinstance(v, int):
        return v
    return {"bottom_left": 0, "bottom_right": nx - 1, "top_left": (ny - 1) * nx, "top_right": ny * nx - 1}[v]


def _finite_trajectory(traj, n_vertices):
    assert traj.positions.ndim == 3 and traj.positions.shape[1:] == (n_vertices, 3)
    assert len(traj) >= 1 and traj.positions.shape[0] == len(traj.times)
    assert np.all(np.isfinite(traj.positions)) and np.all(np.isfinite(traj.times))
    assert np.all(np.diff(traj.times) > 0)


@pytest.mark.slow
@SETTINGS_VALID
@given(valid_scenes())
def test_valid_scene_runs_finite_or_raises_divergence_error(scene):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)   # a tiny max_iterations is allowed to warn
        sim = ic.Simulator(copy.deepcopy(scene))
        n = sim.model.n
        kind = "implicit" if sim.integrator.implicit else "explicit"
        try:
            traj = sim.run()
        except ic.DivergenceError as err:
            event(f"{kind}: diverged")
            assert err.reason and "\n" not in err.reason
            assert err.trajectory is not None and err.trajectory.report["status"] == "diverged"
            _finite_trajectory(err.trajectory, n)
            return
    event(f"{kind}: ok")
    rep = traj.report
    # a valid scene may warn (energy created by an explicit step, a strain bound exceeded): then it says which
    assert rep["status"] in ("ok", "warning")
    assert (rep["status"] == "ok") == (rep["reason"] == "") == (rep["health"] == [])
    for w in rep["health"]:
        assert w["criterion"] in ("energy", "strain", "failsafe", "solver") and w["count"] >= 1
        assert math.isfinite(w["first_time"]) and "\n" not in w["message"]
    _finite_trajectory(traj, n)
    assert len(traj) >= 2                                  # the initial state and the last step
    for key in ("kinetic", "potential", "total", "max_strain"):
        assert np.all(np.isfinite(rep["frames"][key])), key
    assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))


# --------------------------------------------------------------------------- invalid scenes
COMMON_BAD = [None, "1", "abc", True, False, {"x": 1}, [], NAN, INF, -INF, 10**400, -10**5000,
              datetime.date(2020, 1, 1), b"1", 1j, np.bool_(True)]
BAD = {
    "pos": COMMON_BAD + [0, 0.0, -0.0, -1, -1e-300, -5e-324],
    "nonneg": COMMON_BAD + [-1, -1e-9, -1e300],
    "ge1": COMMON_BAD + [0.999, 0, -1],
    "tol": COMMON_BAD + [0, 1.0000001, 2, -1e-3],
    "iters": COMMON_BAD + [0, -1, 2.0, 1.5, 10**6 + 1, np.float64(10)],
    "choice": COMMON_BAD + ["", "nonsense", "XZ", 5, ["xz"]],
    "bool": [None, "1", "true", "abc", {"x": 1}, [], [True], NAN, 0, 1, 1.0, 10**400, datetime.date(2020, 1, 1),
             b"1", 1j],
    "halvings": COMMON_BAD + [-1, 31, 2.0, 1.5, np.float64(3)],
    "count1": COMMON_BAD + [0, -1, 2.0, 1.5, np.float64(3)],
    "vec3": COMMON_BAD + [[0, 0], [0, 0, 0, 0], [NAN, 0, 0], [0, INF, 0], ["0", 0, 0], [None, 0, 0], [True, 0, 0],
                          0.0, "0 0 0", [[0], 0, 0], [10**400, 0, 0], np.zeros(2), np.zeros((3, 1))],
    "vec2pos": COMMON_BAD + [[1.0], [1, 1, 1], [0, 1], [-1, 1], [NAN, 1], [1, INF], ["1", 1], 1.0, [1, -0.0]],
    "res": COMMON_BAD + [[1, 4], [4], [4, 4, 4], [2.5, 4], ["4", 4], 4, [True, 4], [10**6, 10**6], [0, 4],
                         [-3, 4], [NAN, 4], [4, None], np.array([4.0, 4.0])],
    "pins": [None, "top_left", 5, True, {"x": 1}, [-1], [1.5], ["nowhere"], [True], [None], [[0]], [NAN],
             [{"velocity": [0, 0, 0]}], [{"vertices": []}], [{"vertices": [0], "velocity": [0, 0]}],
             [{"vertices": [0], "speed": 1}], [{"vertices": "top_left"}], [10**6], [{"vertices": [10**6]}], [10**5000],
             [0, {"vertices": [0], "velocity": [0, 0, 1]}], [{"vertices": [0], "velocity": [0, NAN, 0]}]],
}
SCHEMA = {
    "simulation.integrator": "choice", "simulation.dt": "pos", "simulation.duration": "pos",
    "simulation.frame_rate": "pos", "simulation.divergence_factor": "ge1",
    "simulation.adaptive.enabled": "bool", "simulation.adaptive.max_halvings": "halvings",
    "simulation.adaptive.grow_after": "count1", "simulation.adaptive.max_strain": "pos",
    "simulation.adaptive.max_energy_growth": "nonneg", "simulation.adaptive.retry_unconverged": "bool",
    "simulation.strain_limit.max_strain": "pos", "simulation.strain_limit.iterations": "count1",
    "solver.tolerance": "tol", "solver.max_iterations": "iters", "solver.preconditioner": "choice",
    "cloth.size": "vec2pos", "cloth.resolution": "res", "cloth.center": "vec3", "cloth.plane": "choice",
    "cloth.mass": "pos", "cloth.density": "pos", "cloth.velocity": "vec3", "cloth.pins": "pins",
    "cloth.material": "choice",
    **{f"cloth.springs.{k}.{p}": "nonneg" for k in sc.SPRING_KINDS for p in ("stiffness", "damping")},
    "effects.gravity": "vec3", "effects.drag": "nonneg", "effects.wind.velocity": "vec3",
}
TABLES = {"": sc.TOP_KEYS, "simulation": sc.SIM_KEYS, "solver": sc.SOLVER_KEYS, "cloth": sc.CLOTH_KEYS,
          "cloth.springs": sc.SPRING_KINDS, "effects": config.EFFECTS.names(), "effects.wind": ("velocity",),
          "simulation.adaptive": sc.ADAPTIVE_KEYS, "simulation.strain_limit": sc.STRAIN_LIMIT_KEYS,
          **{f"cloth.springs.{k}": ("stiffness", "damping") for k in sc.SPRING_KINDS}}


def _get(d, path):
    for k in path.split(".") if path else []:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _set(d, path, value):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = value


def _not_a_table(table: str, value) -> str:
    """The expected start of the error for ``value`` where the table ``table`` belongs."""
    if table == "cloth" and isinstance(value, (list, tuple)):     # [[cloth]]: an array of cloth tables
        return "cloth[0]: must be a table, got " if value else "cloth: must be a table or a non-empty"
    return f"{table}: must be a table, got "


@st.composite
def invalid_scenes(draw):
    """(scene, expected start of the SceneError message)."""
    scene = copy.deepcopy(draw(valid_scenes()))
    cloth = scene["cloth"]
    kind = draw(st.sampled_from(["bad_value"] * 4 + ["unknown_key", "not_a_table", "missing", "conflict",
                                                      "not_a_scene"]))
    event(f"mutation: {kind}")
    if kind == "bad_value":
        path = draw(st.sampled_from(sorted(SCHEMA)))
        if path in ("cloth.mass", "cloth.density"):    # mutate the one the scene uses (both would be a conflict)
            path = "cloth.density" if "density" in cloth else "cloth.mass" if "mass" in cloth else path
        _set(scene, path, draw(st.sampled_from(BAD[SCHEMA[path]])))
        return scene, path
    if kind == "unknown_key":
        tables = [t for t in TABLES if isinstance(_get(scene, t) if t else scene, dict)]
        table = draw(st.sampled_from(tables))
        key = draw(st.text(string.ascii_lowercase + "_", min_size=1, max_size=12).filter(
            lambda k: k not in TABLES[table]))
        target = _get(scene, table) if table else scene
        target[key] = draw(st.one_of(st.integers(), st.floats(), st.text(max_size=5), st.none()))
        return scene, f"{table}.{key}: unknown key" if table else f"{key}: unknown key"
    if kind == "not_a_table":
        tables = ["simulation", "solver", "cloth", "effects", "cloth.springs", "effects.wind",
                  "simulation.adaptive", "simulation.strain_limit"]
        tables += [f"cloth.springs.{k}" for k in sc.SPRING_KINDS]
        table = draw(st.sampled_from(tables))
        value = draw(st.sampled_from([5, 1.5, "x", [1, 2], [], True, None, ("a",)]))
        _set(scene, table, value)
        return scene, _not_a_table(table, value)
    if kind == "missing":
        options = [("cloth", "cloth: missing")]
        if "material" not in cloth:
            if "mass" in cloth or "density" in cloth:
                options.append(("cloth.mass" if "mass" in cloth else "cloth.density", "cloth.mass: missing"))
            for k, spec in cloth.get("springs", {}).items():
                if "stiffness" in spec:
                    options.append((f"cloth.springs.{k}.stiffness", f"cloth.springs.{k}.stiffness: missing"))
        if "strain_limit" in scene.get("simulation", {}):
            options.append(("simulation.strain_limit.max_strain", "simulation.strain_limit.max_strain: missing"))
        if "wind" in scene.get("effects", {}):
            options += [("effects.drag", "effects.drag: missing"),
                        ("effects.wind.velocity", "effects.wind.velocity: missing")]
        path, expect = draw(st.sampled_from(options))
        keys = path.split(".")
        del _get(scene, ".".join(keys[:-1]))[keys[-1]]
        return scene, expect
    if kind == "conflict":
        which = draw(st.sampled_from(["mass+density", "scale", "translation", "mesh"]))
        if which == "mass+density":
            cloth["mass"], cloth["density"] = 0.1, 0.2
            return scene, "cloth.density: give either cloth.mass or cloth.density, not both"
        if which in ("scale", "translation"):
            cloth[which] = 1.0 if which == "scale" else [0.0, 0.0, 0.0]
            return scene, f"cloth.{which}: only used with cloth.mesh"
        cloth["mesh"] = "no_such_mesh.obj"    # with grid keys: not used with a mesh; without: file not found
        return scene, "cloth."
    # (a str or os.PathLike is a scene file path for Simulator: covered by test_scene.test_load_scene_errors)
    return draw(st.sampled_from([[scene], None, 5, 3.5, (), True])), "scene: must be a table, got "


@SETTINGS_INVALID
@given(invalid_scenes())
def test_invalid_scene_raises_scene_error(case):
    scene, expect = case
    with pytest.raises(ic.SceneError) as exc:
        ic.Simulator(scene)
    msg = str(exc.value)
    assert msg.startswith(expect), (msg, expect)
    assert "\n" not in msg and len(msg) < 600


# --------------------------------------------------------------------------- extreme values outside the ranges above
@pytest.mark.filterwarnings("ignore::implicit_cloth.SolverWarning")   # unconverged solves are expected here
@pytest.mark.parametrize("k", [1e16, 1e20, 1e40])
def test_extreme_stiffness_to_mass_ratio(k):
    """k dt^2 / m_i = 1.6e14 .. 1.6e38: the multigrid's coarse Cholesky falls back to a shifted factor (no
    LinAlgError); the run either finishes finite or stops with a DivergenceError whose frames are finite."""
    d = {"simulation": {"dt": 0.01, "duration": 0.03},
         "cloth": {"resolution": [4, 4], "mass": 0.1, "pins": ["top_left"],
                   "springs": {"structural": {"stiffness": k}}},
         "effects": {"gravity": [0.0, 0.0, -9.81]}}
    sim = ic.Simulator(d)
    try:
        traj = sim.run()
    except ic.DivergenceError as err:
        traj = err.trajectory
        assert err.reason and traj.report["status"] == "diverged"
    assert len(traj) >= 1 and np.all(np.isfinite(traj.positions))
    assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))


@pytest.mark.parametrize("call,path", [("solver", "solver: "), ("run_duration", "simulation.duration: "),
                                       ("run_frames", "simulation.frame_rate: "),
                                       ("run_nan", "simulation.duration: ")])
def test_simulator_arguments_outside_the_scene(call, path):
    d = {"cloth": {"resolution": [3, 3], "mass": 0.1}}
    with pytest.raises(ic.SceneError) as exc:
        if call == "solver":
            ic.Simulator(d, solver=5)
        elif call == "run_duration":
            ic.Simulator(d).run(duration=1e300)
        elif call == "run_frames":
            ic.Simulator(d, dt=1e-9).run(duration=1.0, frame_rate=1e9)
        else:
            ic.Simulator(d).run(duration=float("nan"))
    msg = str(exc.value)
    assert msg.startswith(path) and "\n" not in msg, msg
