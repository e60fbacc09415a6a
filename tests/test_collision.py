"""Collisions: scene keys, signed distances, sweeps, time of impact, and cloth against obstacles.

The cloth tests check every kept frame: no cloth vertex inside an obstacle and
no point sampled along any cloth edge inside it, with a tolerance of a small
fraction of the thickness.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

import implicit_cloth as ic
from implicit_cloth.collision import ccd, shapes

TH = 0.005                                  # thickness used by the cloth scenes, m
TOL = 0.1 * TH                              # allowed depth inside an obstacle, m


# --------------------------------------------------------------------------- scenes
def cloth_scene(obstacle, *, dt=1 / 60, duration=0.5, res=16, size=0.6, center=(0.0, 0.0, 0.15),
                plane="xy", pins=(), friction=None, gravity=(0.0, 0.0, -9.81), collision=None, **sim):
    ob = dict(obstacle)
    if friction is not None:
        ob["friction"] = friction
    return {
        "simulation": {"dt": dt, "duration": duration, "frame_rate": 60, **sim},
        "cloth": {"size": [size, size], "resolution": [res, res], "center": list(center), "plane": plane,
                  "mass": 0.1, "pins": list(pins),
                  "springs": {"structural": {"stiffness": 1000.0, "damping": 0.5},
                              "shear": {"stiffness": 100.0, "damping": 0.1},
                              "bend": {"stiffness": 2.0, "damping": 0.01}}},
        "effects": {"gravity": list(gravity), "drag": 0.1},
        "obstacles": [ob],
        "collision": {"thickness": TH, **(collision or {})},
    }


def depths(sim: ic.Simulator, traj: ic.Trajectory, samples: int = 9) -> tuple[float, float]:
    """Largest depth inside the obstacle over all frames: of vertices, and of points along edges, m."""
    col = sim.collider
    ob = col.obstacles[0]
    e = col.edges
    s = np.linspace(0.0, 1.0, samples)
    worst_v = worst_e = 0.0
    for x, t in zip(traj.positions, traj.times):
        p = ob.motion.to_local(x, t)
        worst_v = max(worst_v, float(np.max(-ob.shape.distance(p))))
        pe = p[e[:, 0], None] * (1 - s)[None, :, None] + p[e[:, 1], None] * s[None, :, None]
        worst_e = max(worst_e, float(np.max(-ob.shape.distance(pe.reshape(-1, 3)))))
    return worst_v, worst_e


# --------------------------------------------------------------------------- scene keys
def test_scene_without_obstacles_does_not_import_collision_or_fcl():
    code = ("import sys, implicit_cloth as ic\n"
            "s = ic.Simulator({'cloth': {'mass': 0.1, 'resolution': [4, 4]}, 'effects': {'gravity': [0, 0, -9.81]}})\n"
            "s.step(2)\n"
            "assert s.collider is None\n"
            "print('fcl' in sys.modules, 'implicit_cloth.collision' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_obstacle_defaults_and_effects_list():
    sc = ic.Scene.from_dict(cloth_scene({"shape": "sphere", "radius": 0.2}))
    ob = sc.data["obstacles"][0]
    assert ob["center"] == [0.0, 0.0, 0.0] and ob["velocity"] == [0.0, 0.0, 0.0] and ob["friction"] == 0.0
    assert sc.data["collision"] == {"thickness": TH, "restitution": 0.0, "max_iterations": 8, "newton_iterations": 2}
    assert "collision" in sc.effects
    plain = ic.Scene.from_dict({"cloth": {"mass": 0.1}})
    assert plain.data["obstacles"] == [] and plain.data["collision"] is None


@pytest.mark.parametrize("obstacles, collision, message", [
    ([{"shape": "sphere"}], None, "obstacles[0].radius: missing"),
    ([{"shape": "sphere", "radius": -1}], None, "obstacles[0].radius: must be a finite number > 0, got -1"),
    ([{"shape": "spere", "radius": 1}], None, "obstacles[0].shape: must be one of sphere, box, cone, capsule, "
                                              "plane, mesh (did you mean 'sphere'?), got 'spere'"),
    ([{"shape": "box", "size": [1, 1]}], None, "obstacles[0].size: must be a list of 3 numbers"),
    ([{"shape": "sphere", "radius": 1}, {"shape": "cone", "radius": 1, "height": 1, "axis": [0, 0, 0]}], None,
     "obstacles[1].axis: must be a non-zero direction, got [0, 0, 0]"),
    ([{"shape": "plane", "radius": 1}], None, "obstacles[0].radius: unknown key"),
    ([{"shape": "sphere", "radius": 1, "frictoin": 0.2}], None, "(did you mean 'friction'?)"),
    ([{"shape": "sphere", "radius": 1, "friction": -0.1}], None, "obstacles[0].friction: must be a finite number >= 0"),
    ([{"shape": "sphere", "radius": 1}], {"thickness": 0}, "collision.thickness: must be a finite number > 0, got 0"),
    ([{"shape": "sphere", "radius": 1}], {"restitution": 1.5}, "collision.restitution: must be a finite number >= 0 "
                                                               "and <= 1, got 1.5"),
    ([{"shape": "sphere", "radius": 1}], {"newton_iterations": 0}, "collision.newton_iterations: must be an integer "
                                                                   ">= 1 and <= 100, got 0"),
    ([], {"thickness": 0.01}, "collision: given, but the scene has no [[obstacles]]"),
    ({"shape": "sphere"}, None, "obstacles: must be an array of tables"),
])
def test_bad_obstacle_keys_name_the_path(obstacles, collision, message):
    d = {"cloth": {"mass": 0.1}, "obstacles": obstacles}
    if collision is not None:
        d["collision"] = collision
    with pytest.raises(ic.SceneError) as err:
        ic.Scene.from_dict(d)
    assert message in str(err.value)


# --------------------------------------------------------------------------- signed distances
def _brute_signed_distance(mesh: trimesh.Trimesh, p: np.ndarray) -> np.ndarray:
    """Distance to the nearest triangle by brute force over all of them; negative inside (convex mesh)."""
    tri = mesh.triangles
    k, t = len(p), len(tri)
    P = np.repeat(p, t, axis=0)
    q, _ = ccd.point_triangle_closest(P, np.tile(tri[:, 0], (k, 1)), np.tile(tri[:, 1], (k, 1)),
                                      np.tile(tri[:, 2], (k, 1)))
    d = np.linalg.norm(P - q, axis=1).reshape(k, t).min(axis=1)
    inside = np.all((p @ mesh.face_normals.T) - np.einsum("ij,ij->i", mesh.face_normals, tri[:, 0]) < 0, axis=1)
    return np.where(inside, -d, d)


@pytest.mark.parametrize("shape, mesh, tol", [
    (shapes.Sphere(0.3), trimesh.creation.icosphere(subdivisions=4, radius=0.3), 1e-3),
    (shapes.Box([0.4, 0.2, 0.6]), trimesh.creation.box(extents=[0.4, 0.2, 0.6]), 1e-12),
    (shapes.Capsule(0.15, 0.5), trimesh.creation.capsule(height=0.5, radius=0.15, count=[64, 64]), 1e-3),
    (shapes.Cone(0.25, 0.4), trimesh.creation.cone(radius=0.25, height=0.4, sections=512), 2e-5),
])
def test_signed_distance_matches_brute_force_on_a_fine_mesh(shape, mesh, tol):
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.5, 0.5, (120, 3)) + (mesh.bounds.mean(axis=0))
    ref = _brute_signed_distance(mesh, p)
    phi = shape.distance(p)
    assert np.max(np.abs(phi - ref)) < tol


@pytest.mark.parametrize("shape", [shapes.Sphere(0.3), shapes.Box([0.4, 0.2, 0.6]), shapes.Capsule(0.15, 0.5),
                                   shapes.Cone(0.25, 0.4)])
def test_normal_is_the_gradient_and_closest_point_is_on_the_surface(shape):
    rng = np.random.default_rng(2)
    p = rng.uniform(-0.6, 0.6, (200, 3))
    phi, n, c = shape.closest(p)
    h = 1e-6
    grad = np.stack([(shape.distance(p + h * e) - shape.distance(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    smooth = np.linalg.norm(grad, axis=1) > 0.999          # away from the medial axis (kinks of phi)
    assert smooth.mean() > 0.9
    assert np.allclose(n[smooth], grad[smooth], atol=1e-5)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.allclose(shape.distance(c), 0.0, atol=1e-9)
    assert np.allclose(np.linalg.norm(p - c, axis=1), np.abs(phi), atol=1e-9)


@pytest.mark.parametrize("shape", [shapes.Sphere(0.3), shapes.Capsule(0.15, 0.5), shapes.Cone(0.25, 0.4)])
def test_edge_detection_skips_by_exact_distance_to_the_same_planes(shape):
    """The curved shapes' signed distances are exact (1-Lipschitz: checked on pairs of points), so contact
    detection's edge test skips the edges whose nearer end is farther than the thickness plus half the edge:
    the planes it finds are those of the bounding-box test, bit for bit, on cloth edges of every length
    around the shape, within and beyond the thickness."""
    from implicit_cloth.collision import contacts

    assert shape.exact_distance
    rng = np.random.default_rng(3)
    a = rng.uniform(-0.6, 0.6, (4000, 3))
    b = a + rng.normal(0.0, 0.05, (4000, 3))
    gap = np.abs(shape.distance(a) - shape.distance(b))
    assert np.all(gap <= np.linalg.norm(a - b, axis=1) * (1 + 1e-12) + 1e-15)
    # edges whose points lie near the surface: points on it pushed out by up to 2 thicknesses, edges of
    # 1-120 mm around them, half of them tangent there (their middles nearer than their ends)
    th = 0.005
    _, n, c = shape.closest(rng.uniform(-0.6, 0.6, (3000, 3)))
    mid = c + n * rng.uniform(-0.2 * th, 2 * th, (3000, 1))
    half = rng.normal(0.0, 1.0, (3000, 3))
    half[:1500] -= np.einsum("ij,ij->i", half[:1500], n[:1500])[:, None] * n[:1500]   # tangent: sagging
    half *= (rng.uniform(0.0005, 0.06, 3000) / np.linalg.norm(half, axis=1))[:, None]
    x = np.concatenate([mid - half, mid + half])
    edges = np.column_stack([np.arange(3000), np.arange(3000) + 3000])
    for reach in (0.0, 0.25 * th):
        frame = contacts.Frame(x, x, 0.0, 0.0, th, edges, np.zeros((0, 3), dtype=np.int64),
                               np.ones(len(x), dtype=bool), reach=reach)
        fast = contacts._edge_interiors(frame, 0, shape, x)

        class Boxed(type(shape)):                # the same shape without the exact-distance test
            exact_distance = False
        boxed = Boxed.__new__(Boxed)
        boxed.__dict__.update(shape.__dict__)
        ref = contacts._edge_interiors(frame, 0, boxed, x)
        assert len(ref.idx) > 100
        for name in ("idx", "ob", "n", "off", "point", "kind", "viol"):
            assert np.array_equal(getattr(fast, name), getattr(ref, name)), name


# --------------------------------------------------------------------------- sweeps and time of impact
def test_sweep_closed_forms_plane_sphere_cone_tip():
    r = TH
    p0 = np.array([[0.1, -0.2, 0.9]])
    p1 = np.array([[0.1, -0.2, -0.3]])
    # plane z = 0: z(s) = r
    assert shapes.Plane().sweep(p0, p1, r)[0] == pytest.approx((0.9 - r) / 1.2, rel=1e-12)
    # sphere of radius R at the origin, straight down the z axis
    R = 0.4
    s = shapes.Sphere(R).sweep(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]]), r)[0]
    assert s == pytest.approx((1.0 - R - r) / 2.0, rel=1e-12)
    # off-axis: |p0 + s d|^2 = (R + r)^2 solved by hand
    a, b = np.array([0.1, 0.2, 1.0]), np.array([0.1, 0.2, -1.0])
    z = np.sqrt((R + r) ** 2 - 0.05)
    s = shapes.Sphere(R).sweep(a[None], b[None], r)[0]
    assert s == pytest.approx((1.0 - z) / 2.0, rel=1e-12)
    hit = a + s * (b - a)
    _, n, c = shapes.Sphere(R).closest(hit[None])
    assert np.allclose(n[0], hit / (R + r)) and np.allclose(c[0], R * hit / (R + r))
    # the plane's normal and nearest point
    s = shapes.Plane().sweep(p0, p1, r)[0]
    _, n, c = shapes.Plane().closest(p0 + s * (p1 - p0))
    assert np.allclose(n, [[0, 0, 1]]) and np.allclose(c, [[0.1, -0.2, 0.0]])
    # cone tip: a vertex falling onto the apex stops at H + r, with the normal straight up
    cone = shapes.Cone(0.25, 0.4)
    s = cone.sweep(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 0.0]]), r)[0]
    assert s == pytest.approx((1.0 - 0.4 - r) / 1.0, abs=r * shapes.SWEEP_TOLERANCE)
    _, n, c = cone.closest(np.array([[0.0, 0.0, 1.0 - s]]))
    assert np.allclose(n, [[0, 0, 1]]) and np.allclose(c, [[0, 0, 0.4]])
    # a miss is inf, a start inside is 0
    assert np.isinf(cone.sweep(np.array([[1.0, 0, 1]]), np.array([[1.0, 0, 0]]), r)[0])
    assert cone.sweep(np.array([[0.0, 0, 0.1]]), np.array([[0.0, 0, 1]]), r)[0] == 0.0


def test_sweep_never_stops_inside_the_inflated_shape():
    rng = np.random.default_rng(3)
    for shape in (shapes.Box([0.4, 0.2, 0.6]), shapes.Capsule(0.15, 0.5), shapes.Cone(0.25, 0.4)):
        p0 = rng.uniform(-1, 1, (400, 3))
        p0 = p0[shape.distance(p0) > 2 * TH]
        p1 = rng.uniform(-0.3, 0.3, (len(p0), 3))
        s = shape.sweep(p0, p1, TH)
        hit = np.isfinite(s)
        assert hit.mean() > 0.3
        q = p0[hit] + s[hit, None] * (p1[hit] - p0[hit])
        phi = shape.distance(q)
        assert np.all(phi >= TH * (1 - 1e-9))
        assert np.mean(phi <= TH * (1 + shapes.SWEEP_TOLERANCE) + 1e-9) > 0.95
        # nothing earlier on the path came within r (dense sampling of the misses and the hit paths)
        u = np.linspace(0, 1, 200)
        for k in np.flatnonzero(hit)[:50]:
            pts = p0[k] + np.outer(u[u < s[k] * (1 - 1e-6)], p1[k] - p0[k])
            assert np.all(shape.distance(pts) > TH * (1 - 1e-9))
        for k in np.flatnonzero(~hit)[:50]:
            assert np.all(shape.distance(p0[k] + np.outer(u, p1[k] - p0[k])) > TH * (1 - 1e-9))



def test_sweep_matches_fcl_continuous_collision():
    """fcl's conservative advancement (GJK solver), a sphere of radius r moving against each primitive.

    fcl reports only paths that end in contact, and its sphere-box advancement
    misses some of those (it returns 1.0): such paths are checked on our side only.
    """
    fcl = pytest.importorskip("fcl")
    rng = np.random.default_rng(4)
    cases = [
        (shapes.Sphere(0.3), fcl.Sphere(0.3), np.zeros(3)),
        (shapes.Box([0.4, 0.2, 0.6]), fcl.Box(0.4, 0.2, 0.6), np.zeros(3)),
        (shapes.Capsule(0.15, 0.5), fcl.Capsule(0.15, 0.5), np.zeros(3)),
        (shapes.Cone(0.25, 0.4), fcl.Cone(0.25, 0.4), np.array([0.0, 0.0, 0.2])),   # fcl's cone is centred
    ]
    req_args = dict(num_max_iterations=200, toc_err=1e-7, ccd_motion_type=fcl.CCDMotionType.CCDM_TRANS,
                    gjk_solver_type=fcl.GJKSolverType.GST_INDEP,
                    ccd_solver_type=fcl.CCDSolverType.CCDC_CONSERVATIVE_ADVANCEMENT)
    compared = 0
    for shape, geom, offset in cases:
        obstacle = fcl.CollisionObject(geom, fcl.Transform(offset))
        for _ in range(12):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            p0 = 0.8 * d + rng.uniform(-0.05, 0.05, 3)
            p1 = rng.uniform(-0.05, 0.05, 3) + offset         # ends inside: fcl reports only such hits
            ours = shape.sweep(p0[None], p1[None], TH)[0]
            probe = fcl.CollisionObject(fcl.Sphere(TH), fcl.Transform(p0))
            toc = fcl.continuousCollide(probe, fcl.Transform(p1), obstacle, fcl.Transform(offset),
                                        fcl.ContinuousCollisionRequest(**req_args), fcl.ContinuousCollisionResult())
            if toc < 1.0:
                assert ours == pytest.approx(toc, abs=2e-4)
                compared += 1
            else:   # fcl's sphere-box advancement misses some hits; ours is checked directly
                assert shape.name == "box"
                assert shape.distance((p0 + ours * (p1 - p0))[None])[0] == pytest.approx(TH, rel=2e-3)
    assert compared >= 40


def test_point_triangle_toi_against_dense_sampling():
    rng = np.random.default_rng(5)
    k = 300
    a0, b0, c0 = (rng.uniform(-1, 1, (k, 3)) for _ in range(3))
    a1, b1, c1 = (x + rng.uniform(-0.5, 0.5, (k, 3)) for x in (a0, b0, c0))
    p0 = (a0 + b0 + c0) / 3 + rng.normal(size=(k, 3)) * 0.6
    p1 = (a1 + b1 + c1) / 3 - (p0 - (a0 + b0 + c0) / 3) + rng.normal(size=(k, 3)) * 0.1
    s, side = ccd.point_triangle_toi(p0, p1, a0, a1, b0, b1, c0, c1, tol=1e-6)
    hit = np.isfinite(s)
    assert 0.2 < hit.mean() < 1.0
    # at the reported time the point lies in the triangle
    lerp = lambda x0, x1, t: x0 + t[:, None] * (x1 - x0)  # noqa: E731
    sh = s[hit]
    q, _ = ccd.point_triangle_closest(lerp(p0[hit], p1[hit], sh), lerp(a0[hit], a1[hit], sh),
                                      lerp(b0[hit], b1[hit], sh), lerp(c0[hit], c1[hit], sh))
    assert np.max(np.linalg.norm(q - lerp(p0[hit], p1[hit], sh), axis=1)) < 1e-6
    # sampling: the signed volume changes sign with the point inside only after the reported time
    u = np.linspace(0, 1, 2001)
    for i in range(k):
        t = np.full(len(u), 0.0) + u
        P, A, B, C = (lerp(np.repeat(x0[i:i + 1], len(u), 0), np.repeat(x1[i:i + 1], len(u), 0), t)
                      for x0, x1 in ((p0, p1), (a0, a1), (b0, b1), (c0, c1)))
        f = np.einsum("ij,ij->i", np.cross(B - A, C - A), P - A)
        ch = np.flatnonzero(np.sign(f[:-1]) != np.sign(f[1:]))
        if not len(ch):
            assert not hit[i] or s[i] == 0.0
            continue
        qq, _ = ccd.point_triangle_closest(P[ch], A[ch], B[ch], C[ch])
        inside = np.linalg.norm(qq - P[ch], axis=1) < 1e-2
        if hit[i]:
            assert u[ch[0]] - 1e-3 <= s[i] or not inside[: np.searchsorted(u[ch], s[i])].any()
            assert np.any(np.abs(u[ch] - s[i]) < 1e-3)
        else:
            assert not np.any(np.linalg.norm(qq - P[ch], axis=1) < 1e-4)


def test_edge_edge_toi_closed_form():
    # edge along x at z = 1 - 2 s (falling), fixed edge along y at z = 0: they meet at s = 1/2
    p0, q0 = np.array([[-1.0, 0.3, 1.0]]), np.array([[1.0, 0.3, 1.0]])
    p1, q1 = p0 - [0, 0, 2], q0 - [0, 0, 2]
    u, w = np.array([[0.2, -1.0, 0.0]]), np.array([[0.2, 1.0, 0.0]])
    s, side = ccd.edge_edge_toi(p0, p1, q0, q1, u, u, w, w, tol=1e-9)
    assert s[0] == pytest.approx(0.5, abs=1e-12)
    n = np.cross(q0 - p0, w - u)[0]                      # the feature was on the -z side of the cloth edge
    assert side[0] == np.sign(n @ (u[0] - p0[0]))
    # shifted past the end of the fixed edge: a miss
    s, _ = ccd.edge_edge_toi(p0 + [0, 2, 0], p1 + [0, 2, 0], q0 + [0, 2, 0], q1 + [0, 2, 0], u, u, w, w, tol=1e-9)
    assert np.isinf(s[0])


def test_toi_against_a_still_obstacle_equals_the_general_cubic():
    """A triangle or edge that does not move (an obstacle's, passed as the same array for both ends) takes the
    exact linear (point-triangle) or quadratic (edge-edge) coplanarity function instead of the sampled cubic:
    the same hits, times of impact (to the cubic's bisection, 1e-12) and sides as the general path, which is
    given copies so that it cannot tell (pairs within rounding of the plane at an end left out: there either
    may call it a touch)."""
    rng = np.random.default_rng(11)
    k = 4000
    a, b, c = (rng.uniform(-1, 1, (k, 3)) for _ in range(3))
    p0 = (a + b + c) / 3 + rng.normal(size=(k, 3)) * 0.5
    p1 = (a + b + c) / 3 - (p0 - (a + b + c) / 3) + rng.normal(size=(k, 3)) * 0.2
    q0, q1 = p0 + rng.normal(size=(k, 3)) * 0.4, p1 + rng.normal(size=(k, 3)) * 0.4
    n = np.cross(b - a, c - a)
    def away(f0, f1):
        return (np.abs(f0) > 1e-12) & (np.abs(f1) > 1e-12)

    def edge_f(p, q):
        return np.einsum("ij,ij->i", np.cross(q - p, b - a), a - p)

    for name, fast_args, slow_args, tols, clear in (
            ("point", (p0, p1, a, a, b, b, c, c), (p0, p1, a, a.copy(), b, b.copy(), c, c.copy()), (1e-9, 1e-6, 0.05),
             away(np.einsum("ij,ij->i", n, p0 - a), np.einsum("ij,ij->i", n, p1 - a))),
            ("edge", (p0, p1, q0, q1, a, a, b, b), (p0, p1, q0, q1, a, a.copy(), b, b.copy()), (1e-6, 0.05),
             away(edge_f(p0, q0), edge_f(p1, q1)))):
        fn = ccd.point_triangle_toi if name == "point" else ccd.edge_edge_toi
        for tol in tols:
            fast, slow = fn(*fast_args, tol), fn(*slow_args, tol)
            hit = np.isfinite(fast[0])
            assert 0.05 < hit[clear].mean() < 0.9, (name, tol)
            assert np.array_equal(hit[clear], np.isfinite(slow[0])[clear]), (name, tol)
            both = hit & clear
            assert np.allclose(fast[0][both], slow[0][both], rtol=0, atol=1e-10), (name, tol)
            assert np.array_equal(fast[1][clear], slow[1][clear]), (name, tol)


# --------------------------------------------------------------------------- cloth against obstacles
DROPS = {
    "sphere": ({"shape": "sphere", "radius": 0.2, "center": [0.0, 0.0, -0.2]}, (0.0, 0.0, 0.1)),
    "box_edge": ({"shape": "box", "size": [0.4, 0.4, 0.3], "center": [0.2, 0.03, -0.15]}, (0.0, 0.0, 0.1)),
    "cone_tip": ({"shape": "cone", "radius": 0.2, "height": 0.3, "center": [0.0, 0.0, -0.3]}, (0.0, 0.0, 0.1)),
    "thin_plate": ({"shape": "box", "size": [0.8, 0.01, 0.3], "center": [0.0, 0.0, -0.15]}, (0.0, 0.0, 0.1)),
}


@pytest.mark.parametrize("dt", [1 / 60, 1 / 30], ids=["dt60", "dt30"])
@pytest.mark.parametrize("name", list(DROPS))
def test_dropped_cloth_never_enters_the_obstacle(name, dt):
    obstacle, center = DROPS[name]
    sim = ic.Simulator(cloth_scene(obstacle, dt=dt, duration=0.5, center=center))
    traj = sim.run()
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL, (v_depth, e_depth)
    rep = traj.report["collision"]
    assert rep["contacts"] > 0 and rep["max_penetration"] <= TOL
    # the cloth came to rest on the obstacle: it did not fall through (nor far past it)
    ob = sim.collider.obstacles[0]
    top = ob.motion.to_world(np.array([[0.0, 0.0, shapes.local_aabb(ob.shape)[1][2]]]), 0.0)[0, 2]
    assert traj.positions[-1][:, 2].max() > top - 0.05


def test_report_has_collision_section_and_timing_column():
    sim = ic.Simulator(cloth_scene(DROPS["sphere"][0], duration=0.3, res=8, center=(0, 0, 0.05)))
    traj = sim.run()
    rep = traj.report
    assert "collision" in rep["effects"]
    c = rep["collision"]
    for key in ("contacts", "candidates", "max_penetration", "failsafe_steps", "time", "earliest_toi"):
        assert key in c
    assert c["candidates"] >= c["max_resting_contacts"] > 0
    assert len(rep["frames"]["t_collision"]) == len(traj)
    assert rep["timing"]["t_collision"] == pytest.approx(sum(rep["frames"]["t_collision"]))
    assert sim.last_step.collision.t_collision >= 0


def test_pinned_vertices_are_never_moved_by_a_collision():
    # the pinned corner starts inside the sphere (its neighbours outside): it stays where the pin holds it
    sc = cloth_scene({"shape": "sphere", "radius": 0.06, "center": [-0.3, 0.3, 0.1]}, res=8, duration=0.2,
                     center=(0, 0, 0.1), pins=["top_left"])
    sim = ic.Simulator(sc)
    x0 = sim.positions[sim.model.pinned].copy()
    sim.run()
    assert np.array_equal(sim.positions[sim.model.pinned], x0)


def test_explicit_integrator_is_kept_out_too():
    sim = ic.Simulator(cloth_scene(DROPS["cone_tip"][0], dt=1 / 3000, duration=0.15, res=6,
                                   center=(0, 0, 0.05)), integrator="symplectic_euler")
    traj = sim.run(frame_rate=60)
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    assert traj.report["collision"]["contacts"] > 0


# --------------------------------------------------------------------------- moving obstacles, rest, friction
def _passes_around(rel: np.ndarray, R: float) -> bool:
    """Every vertex that goes from ahead of a sphere (+y) to behind it between frames did so around it.

    ``rel`` (F, N, 3): positions relative to the sphere's centre. The straight path
    between the two frames must keep 0.9 R from the centre (a vertex crossing the
    sphere's disc passes near the centre); checked on at least one such vertex.
    """
    ahead = rel[..., 1] > 0
    f, v = np.nonzero(ahead[:-1] & ~ahead[1:])
    a, b = rel[f, v], rel[f + 1, v]
    d = b - a
    t = np.clip(-np.einsum("ij,ij->i", a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
    closest = np.linalg.norm(a + t[:, None] * d, axis=1)
    return len(f) > 0 and bool(np.all(closest > 0.9 * R))


@pytest.mark.parametrize("adaptive", [False, True], ids=["fixed", "adaptive"])
@pytest.mark.parametrize("dt", [1 / 60, 1 / 30], ids=["dt60", "dt30"])
def test_fast_sphere_pushes_a_hanging_cloth_and_never_crosses_it(dt, adaptive):
    R = 0.12
    sc = cloth_scene({"shape": "sphere", "radius": R, "center": [0.0, -0.3, 0.0], "velocity": [0.0, 5.0, 0.0]},
                     dt=dt, duration=0.16, res=16, size=0.6, center=(0, 0, 0), plane="xz",
                     pins=["top_left", "top_right"])
    sim = ic.Simulator(sc, adaptive={"enabled": adaptive})
    traj = sim.run(frame_rate=1 / dt)                      # every nominal step is a frame
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    ob = sim.collider.obstacles[0]
    centers = np.array([ob.motion.pose(t)[0] for t in traj.times])
    if not adaptive:
        # a vertex that goes from ahead of the sphere's centre to behind it in one step does so around
        # it: its straight path relative to the sphere stays outside, never through the middle (with
        # adaptive substeps a frame spans several steps, and the straight path between frames is not the path)
        assert _passes_around(traj.positions - centers[:, None, :], R)
    # pushed: the cloth's middle is carried well past where it hung (y = 0), more than the sphere's diameter.
    # Fixed steps of 1/240 and 1/480 s (converged) carry it about 0.32 m before it slides over the sphere;
    # fixed steps of 1/60 s keep it in front (0.58 m) at the price of a strain of 4: adaptive stepping (on by
    # default) follows the converged answer.
    mid = np.argmin(np.linalg.norm(sim.model.rest_positions, axis=1))
    assert traj.positions[-1, mid, 1] > 2 * R


def test_resting_drape_on_a_sphere_settles_without_jitter():
    """A 16² drape on a sphere at dt 1/60 lands and comes to rest: no energy rise late, what rests on the sphere
    still to twice the smoothed friction's sliding speed (1e-4 m/s: a contact loaded to its friction bound
    creeps at about that speed; here the fastest resting vertex moves at 0.9-1.2e-4 m/s at 2.5 s and 1.05-1.1e-4
    from 3 s on, whether the friction's Newton continuation iterates the springs too or keeps them linearised).
    (2.5 s: with the contact steps' Newton continuation, the default since it stopped the creep of drapes at
    dt 1/30, the landing ends a little later.)"""
    sc = cloth_scene({"shape": "sphere", "radius": 0.2, "center": [0.0, 0.0, -0.2]}, dt=1 / 60, duration=2.5,
                     res=16, center=(0, 0, 0.05), friction=0.3)
    sim = ic.Simulator(sc)
    traj = sim.run(frame_rate=10)
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    f = traj.report["frames"]
    late = np.asarray(f["time"]) >= 2.0 - 1e-9
    total = np.asarray(f["total"])[late]
    # energy no longer rises: over the last half second it stays within 0.1 % of what the drop released
    released = f["total"][0] - total[-1]
    assert released > 0.1
    assert np.max(total) - total[0] < 1e-3 * released
    assert np.max(np.asarray(f["kinetic"])[late]) < 1e-6
    speed = np.linalg.norm(sim.velocities, axis=1)                   # m/s
    on = np.isin(np.arange(sim.model.n), sim.collider.held)
    assert on.sum() > 20 and speed[on].max() < 2e-4                  # what rests on the sphere is still
    assert speed.max() < 2e-3                                        # the hanging corners barely sway
    assert traj.report["collision"]["max_resting_contacts"] > 20
    # it rests on the sphere (not slid off): the middle sits on the top
    mid = np.argmin(np.linalg.norm(sim.model.rest_positions[:, :2], axis=1))
    assert sim.positions[mid, 2] == pytest.approx(TH, abs=0.01)


@pytest.mark.parametrize("tan", [0.3, 0.45, 0.55, 0.8])
def test_friction_on_a_tilted_plane_holds_below_and_slides_above_the_friction_angle(tan):
    """Cloth resting on a plane under gravity tilted by theta, Coulomb coefficient mu = 0.5, with Coulomb's
    sticking and sliding states (``friction_speed = 0``; the default smoothed friction creeps below the angle,
    tests/test_smoothed_friction.py).

    Static when tan(theta) < mu; above, backward Euler slides it by the discrete
    constant-acceleration distance a h^2 n (n + 1) / 2, a = g (sin theta - mu cos theta).
    """
    mu, T, h, g = 0.5, 0.5, 1 / 60, 9.81
    th = np.arctan(tan)
    sc = cloth_scene({"shape": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]}, dt=h, duration=T, res=8,
                     size=0.3, center=(0, 0, TH), friction=mu, gravity=(g * np.sin(th), 0.0, -g * np.cos(th)),
                     collision={"friction_speed": 0.0})
    sc["effects"].pop("drag")
    sim = ic.Simulator(sc)
    x0 = sim.positions.copy()
    sim.run()
    d = (sim.positions - x0).mean(axis=0)
    n = round(T / h)
    a = max(0.0, g * (np.sin(th) - mu * np.cos(th)))
    assert d[0] == pytest.approx(a * h * h * n * (n + 1) / 2, abs=1e-9 + 1e-3 * abs(a))
    assert np.allclose(sim.positions[:, 2], TH, atol=1e-9)      # kept on the surface, at the thickness


def test_a_resting_contact_that_leaves_its_friction_cone_slides_in_that_step():
    """A cloth resting (sticking) on a floor that is jerked sideways at 1 m/s: in the jerk's step the carried
    contacts leave their friction cone and slide, so the floor drags the cloth by kinetic friction only, at
    mu g per step (backward Euler: v = n mu g h after n steps), not at the floor's speed. (Before carried
    contacts' slips were solved again within their step, the first step held the cloth to the floor: 1 m/s.)"""
    mu, h, g, t0 = 0.3, 1 / 60, 9.81, 0.2
    floor = {"shape": "plane", "normal": [0, 0, 1],
             "keyframes": [{"time": 0.0, "center": [0.0, 0.0, 0.0]}, {"time": t0, "center": [0.0, 0.0, 0.0]},
                           {"time": t0 + 1.0, "center": [1.0, 0.0, 0.0]}]}
    sc = cloth_scene(floor, dt=h, duration=1.0, res=8, size=0.3, center=(0, 0, TH), friction=mu)
    sc["effects"].pop("drag")
    sim = ic.Simulator(sc)
    sim.step(round(t0 / h))
    assert np.abs(sim.velocities).max() < 1e-9                        # at rest, sticking
    for n in (1, 2, 3):
        sim.step(1)
        vx = sim.velocities[:, 0]
        assert vx == pytest.approx(np.full_like(vx, n * mu * g * h), rel=1e-6)
    assert np.allclose(sim.positions[:, 2], TH, atol=1e-9)


def test_tilted_plane_obstacle_normal_and_restitution():
    """A vertex dropped on a plane with restitution e leaves with e times its normal speed."""
    sc = cloth_scene({"shape": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]}, dt=1 / 100, duration=0.05,
                     res=2, size=0.01, center=(0, 0, 0.02), gravity=(0, 0, 0), collision={"restitution": 0.5})
    sc["effects"].pop("drag")
    sc["cloth"]["velocity"] = [0.0, 0.0, -2.0]
    sim = ic.Simulator(sc)
    sim.step(2)                                               # hits within the second step
    assert np.allclose(sim.velocities[:, 2], 1.0)
    assert np.all(sim.positions[:, 2] >= TH - 1e-12)


def test_readme_collision_block_is_valid_and_runs(tmp_path):
    """The annotated [[obstacles]] / [collision] block of docs/scene.md loads and runs with a cloth."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "scene.md").read_text()
    block = next(b for b in re.findall(r"```toml\n(.*?)```", text, re.S) if "[[obstacles]]" in b)
    path = tmp_path / "c.toml"
    path.write_text('[cloth]\nmass = 0.1\nresolution = [6, 6]\ncenter = [0.0, 0.0, 1.0]\nplane = "xy"\n'
                    '[effects]\ngravity = [0.0, 0.0, -9.81]\n' + block)
    scene = ic.load_scene(path)
    assert [o["shape"] for o in scene.data["obstacles"]] == ["sphere", "box", "cone", "capsule", "plane"]
    sim = ic.Simulator(scene)
    sim.step(3)
    assert len(sim.collider.obstacles) == 5


def test_collision_benchmark_quick(tmp_path):
    """The benchmark's quick mode writes well-formed outputs (no time is asserted)."""
    import json
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, str(root / "benchmarks" / "collision.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    res = json.loads((tmp_path / "collision.json").read_text())
    assert res["benchmark"] == "collision" and res["quick"] is True
    assert [r["resolution"] for r in res["rows"]] == [8, 12]
    for r in res["rows"]:
        assert r["ms_step"] >= r["ms_collision"] >= 0 and r["resting_median"] > 0
        assert r["max_penetration"] == 0.0
    assert "| 12² |" in (tmp_path / "collision.md").read_text()


def test_spinning_box_under_a_falling_cloth():
    """Angular velocity: a bar spinning at 6 rad/s about the vertical catches a falling cloth, nothing enters it."""
    sc = cloth_scene({"shape": "box", "size": [0.5, 0.08, 0.08], "center": [0.0, 0.0, -0.05],
                      "angular_velocity": [0.0, 0.0, 6.0]}, dt=1 / 30, duration=0.4, res=12, center=(0, 0, 0.05),
                     friction=0.3)
    sim = ic.Simulator(sc)
    traj = sim.run(frame_rate=30)
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    assert traj.report["collision"]["contacts"] > 0
    # friction drags the cloth round with the bar: it gains angular momentum about the bar's axis
    x, v = sim.positions, sim.velocities
    lz = float(np.sum(sim.model.masses * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0])))
    assert lz > 0


# --------------------------------------------------------------------------- mesh obstacles
def _mesh_file(tmp_path, mesh: trimesh.Trimesh, name: str = "obstacle.obj") -> str:
    path = tmp_path / name
    mesh.export(str(path))
    return str(path)


def _convex_depth(mesh: trimesh.Trimesh, positions: np.ndarray, edges: np.ndarray, samples: int = 9) -> float:
    """Largest depth of a cloth vertex or edge point inside a convex mesh (face planes), m."""
    s = np.linspace(0.0, 1.0, samples)
    pe = (positions[edges[:, 0], None] * (1 - s)[None, :, None]
          + positions[edges[:, 1], None] * s[None, :, None]).reshape(-1, 3)
    sd = pe @ mesh.face_normals.T - np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles[:, 0])
    return float(max(0.0, np.max(-sd.max(axis=1))))


MESHES = {
    "icosphere": (lambda: trimesh.creation.icosphere(subdivisions=2, radius=0.2), [0.0, 0.0, -0.2]),
    "box_edge": (lambda: trimesh.creation.box(extents=[0.4, 0.4, 0.3]), [0.2, 0.03, -0.15]),
    "cone_tip": (lambda: trimesh.creation.cone(radius=0.2, height=0.3, sections=32), [0.0, 0.0, -0.3]),
}


@pytest.mark.parametrize("dt", [1 / 60, 1 / 30], ids=["dt60", "dt30"])
@pytest.mark.parametrize("name", list(MESHES))
def test_cloth_dropped_on_a_mesh_obstacle_never_enters_it(tmp_path, name, dt):
    make, translation = MESHES[name]
    mesh = make()
    path = _mesh_file(tmp_path, mesh)
    sim = ic.Simulator(cloth_scene({"shape": "mesh", "path": path, "translation": translation}, dt=dt,
                                   duration=0.5, center=(0.0, 0.0, 0.1)))
    traj = sim.run()
    placed = trimesh.Trimesh(mesh.vertices + translation, mesh.faces)
    depth = max(_convex_depth(placed, x, sim.collider.edges) for x in traj.positions)
    assert depth <= TOL
    rep = traj.report["collision"]
    assert rep["contacts"] > 0 and rep["obstacles"] == ["mesh"]
    assert traj.positions[-1][:, 2].max() > placed.bounds[1, 2] - 0.05      # resting on it, not fallen through


def test_open_mesh_is_two_sided(tmp_path):
    """A single square (an open mesh): a cloth dropped on it never passes through it, from either side."""
    square = trimesh.Trimesh([[-0.2, -0.2, 0.0], [0.2, -0.2, 0.0], [0.2, 0.2, 0.0], [-0.2, 0.2, 0.0]],
                             [[0, 1, 2], [0, 2, 3]])
    path = _mesh_file(tmp_path, square)
    for z, g in ((0.05, -9.81), (-0.05, 9.81)):          # from above with gravity down, from below with it up
        sim = ic.Simulator(cloth_scene({"shape": "mesh", "path": path}, dt=1 / 30, duration=0.4, res=12,
                                       center=(0.0, 0.0, z), gravity=(0.0, 0.0, g)))
        traj = sim.run(frame_rate=30)
        x = traj.positions
        inside = (np.abs(x[..., 0]) < 0.2) & (np.abs(x[..., 1]) < 0.2)
        flipped = inside[:-1] & inside[1:] & (np.sign(x[:-1, :, 2]) != np.sign(x[1:, :, 2]))
        assert not flipped.any()
        assert np.all(np.sign(x[-1][inside[-1], 2]) == np.sign(z))
        assert traj.report["collision"]["contacts"] > 0


def test_mesh_feature_normal_cones_against_brute_force():
    """A mesh edge's and vertex's normal cones (``MeshShape.edge_cone``, ``vertex_cone``), two-sided, against the
    definition checked on points of the feature's faces (their corners and 100 samples each): a direction is in
    a vertex's cone when its faces' points all lie on one side of the plane through the vertex normal to it (to
    the tolerance's cosine, 0.05), an edge's (for directions across the edge) when they do for the plane through
    the edge's midpoint. Directions whose decisive cosines lie within 0.03-0.08 of the border are not judged."""
    rng = np.random.default_rng(3)

    def one_side(points, origin, n):
        d = points - origin
        c = d @ n / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        lo, hi = -c.min(), c.max()
        if 0.03 < lo < 0.08 or 0.03 < hi < 0.08:
            return None
        return not (lo > 0.05 and hi > 0.05)

    def face_points(mesh, fs, seed):
        sub = trimesh.Trimesh(mesh.vertices, fs, process=False)
        return np.concatenate([mesh.vertices[fs.ravel()], trimesh.sample.sample_surface(sub, 100, seed=seed)[0]])

    judged = 0
    for mesh in (trimesh.creation.icosphere(subdivisions=2, radius=0.3), trimesh.creation.box(extents=[0.4, 0.3, 0.2])):
        s = shapes.MeshShape(mesh.vertices, mesh.faces)
        n = rng.normal(size=(300, 3))
        n /= np.linalg.norm(n, axis=1)[:, None]
        v = rng.integers(len(s.vertices), size=300)
        got = s.vertex_cone(v, n)
        for k in range(300):
            want = one_side(face_points(mesh, mesh.faces[np.any(mesh.faces == v[k], axis=1)], k), s.vertices[v[k]],
                            n[k])
            if want is not None:
                judged += 1
                assert got[k] == want, (k, "vertex")
        e = rng.integers(len(s.edges), size=300)
        q = s.vertices[s.edges[e]].mean(axis=1)
        t = s.vertices[s.edges[e, 1]] - s.vertices[s.edges[e, 0]]
        t /= np.linalg.norm(t, axis=1)[:, None]
        n -= np.einsum("ij,ij->i", n, t)[:, None] * t          # across the edge, as a closest-point direction is
        n /= np.linalg.norm(n, axis=1)[:, None]
        got = s.edge_cone(e, n, q)
        for k in range(300):
            a, b = s.edges[e[k]]
            fs = mesh.faces[np.sum((mesh.faces == a) | (mesh.faces == b), axis=1) == 2]
            want = one_side(face_points(mesh, fs, k), q[k], n[k])
            if want is not None:
                judged += 1
                assert got[k] == want, (k, "edge")
    assert judged > 1000
    # the top of an icosphere: the outward and inward normals hold, a sideways one does not
    s = shapes.MeshShape(*(lambda m: (m.vertices, m.faces))(trimesh.creation.icosphere(subdivisions=3, radius=0.3)))
    top = int(np.argmax(s.vertices[:, 2]))
    assert s.vertex_cone(np.array([top] * 3), np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]])).tolist() == \
        [True, True, False]


def test_a_cloth_landing_on_a_mesh_sphere_is_held_along_its_surface(tmp_path):
    """Contacts found on a flat 64² cloth's proposed step through the top of a mesh sphere (dt 1/30, the cloth
    falling 6.5 cm) hold it along the surface's outward normal. Cloth edges passing beside the mesh's edges
    gave contacts with sideways normals (a cloth edge near a mesh edge, nearer to a face than to the edge:
    outside the edge's normal cone): holding light vertices in their own plane against the stiff springs sent
    them off at 10 m/s, and the next solves' contacts at up to 1e7 m/s (the contact table's 64² icosphere at
    dt 1/30: adaptive stepping threw those steps away, at three times the cost)."""
    from implicit_cloth.collision import contacts
    path = _mesh_file(tmp_path, trimesh.creation.icosphere(subdivisions=3, radius=0.3))
    sim = ic.Simulator(cloth_scene({"shape": "mesh", "path": path}, dt=1 / 30, res=64, size=1.0,
                                   center=(0.0, 0.0, 0.3365)))
    x0 = sim.positions
    x1 = x0 - [0.0, 0.0, 0.0654]
    c = sim.collider.ctx
    found = contacts.detect(contacts.Frame(x0, x1, 0.0, 1 / 30, c.thickness, c.edges, c.faces, c.free),
                            c.obstacles)
    assert len(found) > 100
    radial = x1[found.idx] / np.linalg.norm(x1[found.idx], axis=1)[:, None]
    assert np.einsum("ij,ij->i", found.n, radial).min() > 0.5


def test_mesh_obstacle_keys(tmp_path):
    path = _mesh_file(tmp_path, trimesh.creation.icosphere(subdivisions=1))
    sc = ic.Scene.from_dict({"cloth": {"mass": 0.1}, "obstacles": [{"shape": "mesh", "path": "obstacle.obj",
                                                                   "scale": 2.0}]}, base_dir=tmp_path)
    ob = sc.data["obstacles"][0]
    assert ob["path"] == path and ob["scale"] == 2.0 and ob["translation"] == [0.0, 0.0, 0.0]
    for bad, msg in (({"shape": "mesh"}, "obstacles[0].path: missing"),
                     ({"shape": "mesh", "path": "nope.obj"}, "obstacles[0].path: file not found, got 'nope.obj'"),
                     ({"shape": "mesh", "path": path, "radius": 1.0}, "obstacles[0].radius: unknown key"),
                     ({"shape": "mesh", "path": path, "scale": 0}, "obstacles[0].scale: must be a finite number > 0")):
        with pytest.raises(ic.SceneError) as err:
            ic.Scene.from_dict({"cloth": {"mass": 0.1}, "obstacles": [bad]}, base_dir=tmp_path)
        assert msg in str(err.value)


def test_assigning_the_state_forgets_resting_contacts():
    sim = ic.Simulator(cloth_scene({"shape": "plane"}, res=6, center=(0, 0, TH)))
    sim.step(3)
    assert len(sim.collider.held) > 0
    sim.positions = sim.positions + [0.0, 0.0, 0.5]
    assert len(sim.collider.held) == 0
    sim.step(1)
    assert sim.last_step.collision.resting == 0


def test_fast_mesh_sphere_pushes_a_hanging_cloth_and_never_crosses_it(tmp_path):
    """A mesh obstacle moving at 5 m/s (the case that passes straight through cloth in simpler engines)."""
    R = 0.12
    path = _mesh_file(tmp_path, trimesh.creation.icosphere(subdivisions=2, radius=R))
    sc = cloth_scene({"shape": "mesh", "path": path, "translation": [0.0, -0.3, 0.0], "velocity": [0.0, 5.0, 0.0]},
                     dt=1 / 30, duration=0.16, res=16, size=0.6, center=(0, 0, 0), plane="xz",
                     pins=["top_left", "top_right"])
    sim = ic.Simulator(sc, adaptive={"enabled": False})    # every step a frame, for _passes_around
    traj = sim.run(frame_rate=30)
    ob = sim.collider.obstacles[0]
    centers = np.array([ob.motion.pose(t)[0] for t in traj.times])
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=R)
    for x, c in zip(traj.positions, centers):
        assert _convex_depth(trimesh.Trimesh(mesh.vertices + c, mesh.faces), x, sim.collider.edges) <= TOL
    assert _passes_around(traj.positions - centers[:, None, :], R)
    mid = np.argmin(np.linalg.norm(sim.model.rest_positions, axis=1))
    assert traj.positions[-1, mid, 1] > 2 * R      # pushed (see the primitive sphere's test above)


def test_bdf2_with_obstacles():
    obstacle, center = DROPS["box_edge"]
    sim = ic.Simulator(cloth_scene(obstacle, dt=1 / 30, duration=0.5, res=12, center=center), integrator="bdf2")
    traj = sim.run()
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    assert traj.report["collision"]["max_resting_contacts"] > 0


def test_cli_summary_has_a_collision_line(tmp_path, capsys):
    from implicit_cloth.cli import main

    scene = tmp_path / "s.toml"
    scene.write_text('[simulation]\nduration = 0.1\n[cloth]\nmass = 0.1\nresolution = [6, 6]\nplane = "xy"\n'
                     'center = [0.0, 0.0, 0.02]\n[effects]\ngravity = [0.0, 0.0, -9.81]\n'
                     '[[obstacles]]\nshape = "plane"\n')
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if s.startswith("collision"))
    assert "plane:" in line and "max penetration 0 m" in line


def test_moving_obstacle_work_is_counted_not_called_divergence():
    """A sphere pushing a pinned cloth does work on it: the report counts it, and the divergence check (here at
    its strictest, factor 1) does not mistake it for a numerical energy gain. At a small fixed step the cloth
    (damped springs, inelastic contact) keeps less than the obstacle gave it."""
    R = 0.12
    sc = cloth_scene({"shape": "sphere", "radius": R, "center": [0.0, -0.3, 0.0], "velocity": [0.0, 5.0, 0.0]},
                     dt=1 / 480, duration=0.16, res=12, size=0.6, center=(0, 0, 0), plane="xz",
                     pins=["top_left", "top_right"])
    traj = ic.Simulator(sc, adaptive={"enabled": False}, divergence_factor=1.0).run(frame_rate=60)
    col = traj.report["collision"]
    e = traj.report["frames"]["total"]
    assert traj.report["status"] == "ok" and col["contacts"] > 0
    gained = e[-1] - e[0]
    assert gained > 0.1 * traj.report["divergence_bound"]["energy_scale"]   # the push is not negligible
    assert gained <= col["work"]


@pytest.mark.parametrize("solver,expect", [({}, (1e-3, 1e-3)), ({"contact_tolerance": 1e-5}, (1e-3, 1e-5)),
                                           ({"tolerance": 1e-6, "contact_tolerance": 1e-4}, (1e-6, 1e-6))])
def test_the_solves_of_steps_with_contacts_use_the_contact_tolerance(solver, expect):
    """A step's solves are at ``solver.tolerance`` until the cloth touches; every solve of a step with
    contacts (the rounds, the carried resting contacts) at ``solver.contact_tolerance`` (default and at most
    ``tolerance``): their impulses decide sticking and sliding. Newton's corrections keep their forcing."""
    obstacle, center = DROPS["sphere"]
    d = cloth_scene(obstacle, dt=1 / 30, duration=0.6, res=10, center=center)
    d["solver"] = dict(solver)
    sim = ic.Simulator(ic.Scene.from_dict(d))
    integ = sim.integrator
    assert (integ.tolerance, integ.contact_tolerance) == expect
    seen = []
    orig = integ._solve

    def spy(A, b, z, filt, info, guess=None, tolerance=None, **kw):
        seen.append((len(filt.partial) + len(filt.fixed) > 0, integ.tolerance if tolerance is None else tolerance))
        return orig(A, b, z, filt, info, guess, tolerance, **kw)

    integ._solve = spy
    r = sim.run().report
    assert r["solver"]["contact_tolerance"] == expect[1]
    free = {t for c, t in seen if not c}
    held = [t for c, t in seen if c]
    assert free == {expect[0]} and len(held) > 10
    assert set(held) <= {expect[1], max(expect[0], 0.1)} and held.count(expect[1]) > 10
