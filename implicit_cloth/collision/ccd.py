"""Vectorised closest points and continuous time of impact for point-triangle and edge-edge pairs.

All positions move linearly over the step: ``x(s) = x0 + s (x1 - x0)``, ``s`` in
[0, 1] (the fraction of the step). A point ``p`` meets the plane of triangle
``(a, b, c)`` when the coplanarity condition

    f(s) = ((b - a) x (c - a)) . (p - a) = 0                     (point-triangle)
    f(s) = ((q - p) x (w - u)) . (u - p) = 0                     (edge pq - edge uw)

holds, a cubic in ``s`` (Provot 1997; Bridson, Fedkiw & Anderson 2002). Its
coefficients are fitted exactly from four samples, its roots in [0, 1] found by
bisection on the (at most three) intervals where it is monotone, bounded by the
roots of ``f'``: robust to double roots and to nearly-degenerate coefficients,
unlike the closed-form cubic formula. At each root, earliest first, the pair is
a hit if the closest points of the two primitives are within ``tol``. The
earliest hit per pair is returned with the sign of ``f`` just before it, which
tells which side of the other primitive the pair came from.
"""

from __future__ import annotations

import numpy as np

#: Bisection iterations per root: (1/2)^40 ~ 1e-12 of the step, far below any length scale of interest.
BISECTION_STEPS = 40

_VANDERMONDE_INV = np.linalg.inv(np.vander(np.array([0.0, 1 / 3, 2 / 3, 1.0]), 4, increasing=True))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def point_triangle_closest(p, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle ``(a, b, c)`` to ``p`` and its barycentric weights.

    Ericson, *Real-Time Collision Detection* (2005), §5.1.5, vectorised over the
    Voronoi regions. Returns the points (K, 3) and weights (K, 3) with
    ``point = w0 a + w1 b + w2 c``.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    w = np.zeros((len(p), 3))
    done = np.zeros(len(p), dtype=bool)

    def put(mask, w0, w1, w2):
        m = mask & ~done
        w[m, 0], w[m, 1], w[m, 2] = w0[m], w1[m], w2[m]
        done[m] = True

    one, zero = np.ones(len(p)), np.zeros(len(p))
    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), one, zero, zero)                           # vertex a
        put((d3 >= 0) & (d4 <= d3), zero, one, zero)                          # vertex b
        put((d6 >= 0) & (d5 <= d6), zero, zero, one)                          # vertex c
        t = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, zero)               # edge ab
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, zero, t)               # edge ac
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), zero, 1 - t, t)  # edge bc
        den = va + vb + vc
        v_, w_ = vb / den, vc / den
        put(np.ones(len(p), dtype=bool), 1 - v_ - w_, v_, w_)                 # face
    bad = ~np.all(np.isfinite(w), axis=1)                                     # degenerate triangle
    if np.any(bad):
        w[bad] = (1.0, 0.0, 0.0)
    q = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    return q, w


def segment_closest(p0, p1, q0, q1) -> tuple[np.ndarray, np.ndarray]:
    """Parameters ``u, v`` in [0, 1] of the closest points ``p0 + u (p1 - p0)`` and ``q0 + v (q1 - q0)``.

    Ericson (2005) §5.1.9, vectorised; parallel and degenerate segments handled.
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c, b = _dot(d1, r), _dot(d1, d2)
    eps = 1e-30
    den = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(den > 1e-12 * np.maximum(a * e, eps), np.clip((b * f - c * e) / den, 0, 1), 0.0)
        v = np.where(e > eps, (b * u + f) / np.where(e > eps, e, 1.0), 0.0)
        lo, hi = v < 0, v > 1
        u = np.where(lo, np.where(a > eps, np.clip(-c / np.where(a > eps, a, 1.0), 0, 1), 0.0), u)
        u = np.where(hi, np.where(a > eps, np.clip((b - c) / np.where(a > eps, a, 1.0), 0, 1), 0.0), u)
    v = np.clip(v, 0.0, 1.0)
    return u, v


def _cubic_roots(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roots in [0, 1] of the cubics through ``samples`` (K, 4) at s = 0, 1/3, 2/3, 1.

    Returns the roots (K, 3), ascending, inf where there are fewer, and the
    coefficients (K, 4) of ``c0 + c1 s + c2 s^2 + c3 s^3`` (:func:`_poly_roots`).
    """
    return _poly_roots(samples @ _VANDERMONDE_INV.T)


def _poly_roots(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roots in [0, 1] of the cubics ``c0 + c1 s + c2 s^2 + c3 s^3`` (coefficients (K, 4)), ascending, inf where
    there are fewer (K, 3), and the coefficients.

    Each row's interval [0, 1] is split at the real roots of the derivative; on
    each monotone piece a sign change (or a zero end) is bisected.
    """
    k = len(c)
    a, b, cc = 3 * c[:, 3], 2 * c[:, 2], c[:, 1]         # f'(s) = a s^2 + b s + cc
    crit = np.full((k, 2), 2.0)                          # 2.0 = "no break point"
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4 * a * cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        quad = np.abs(a) > 1e-14 * (np.abs(b) + np.abs(cc) + 1e-300)
        q = -0.5 * (b + np.copysign(sq, b))
        r1 = np.where(quad, q / a, -cc / b)
        r2 = np.where(quad, cc / q, 2.0)
    ok = disc >= 0
    crit[:, 0] = np.where(ok & np.isfinite(r1), r1, 2.0)
    crit[:, 1] = np.where(ok & np.isfinite(r2), r2, 2.0)
    crit = np.where((crit > 0) & (crit < 1), crit, 2.0)
    crit.sort(axis=1)
    knots = np.column_stack([np.zeros(k), crit, np.ones(k)])
    knots = np.minimum(knots, 1.0)
    knots = np.maximum.accumulate(knots, axis=1)

    def f(s):
        return ((c[:, 3:4] * s + c[:, 2:3]) * s + c[:, 1:2]) * s + c[:, 0:1]

    lo, hi = knots[:, :3].copy(), knots[:, 1:].copy()
    flo, fhi = f(lo), f(hi)
    roots = np.full((k, 3), np.inf)
    zero_lo = flo == 0
    change = (np.sign(flo) * np.sign(fhi) < 0) & ~zero_lo
    r_, j_ = np.nonzero(change)                          # bisect only the intervals with a sign change
    if len(r_):
        cc_ = c[r_]
        a_, b_, fa = lo[r_, j_], hi[r_, j_], flo[r_, j_]
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (a_ + b_)
            fm = ((cc_[:, 3] * mid + cc_[:, 2]) * mid + cc_[:, 1]) * mid + cc_[:, 0]
            left = np.sign(fm) * np.sign(fa) <= 0
            b_ = np.where(left, mid, b_)
            a_ = np.where(left, a_, mid)
            fa = np.where(left, fa, fm)
        roots[r_, j_] = 0.5 * (a_ + b_)
    roots[zero_lo] = knots[:, :3][zero_lo]
    last_zero = (fhi[:, 2] == 0)                         # a zero at s = 1 exactly
    roots[last_zero, 2] = np.minimum(roots[last_zero, 2], 1.0)
    roots.sort(axis=1)
    return roots, c


def _cubic(c: np.ndarray, s: np.ndarray) -> np.ndarray:
    return ((c[:, 3] * s + c[:, 2]) * s + c[:, 1]) * s + c[:, 0]


def _side_before(roots: np.ndarray, coef: np.ndarray, toi: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Sign of f just before the hit (midway from the previous root, or 0, to it); sign f(0) without a hit."""
    k = len(toi)
    prev = np.where(j > 0, roots[np.arange(k), np.maximum(j - 1, 0)], 0.0)
    mid = 0.5 * (np.where(np.isfinite(prev), prev, 0.0) + np.where(np.isfinite(toi), toi, 0.0))
    s = np.where(np.isfinite(toi), mid, 0.0)
    return np.sign(_cubic(coef, s))


def _lerp(x0, x1, s):
    return x0 + s[:, None] * (x1 - x0)


def _linear_roots(f0: np.ndarray, f1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_poly_roots` of the linear ``f0 + (f1 - f0) s``, exactly: the crossing ``f0 / (f0 - f1)`` where the
    sign changes, 0 and 1 where ``f`` is zero there."""
    k = len(f0)
    coef = np.zeros((k, 4))
    coef[:, 0], coef[:, 1] = f0, f1 - f0
    crossing = np.sign(f0) * np.sign(f1) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crossing, f0 / (f0 - f1), np.inf)
    roots = np.full((k, 3), np.inf)
    zero0, zero1 = f0 == 0, f1 == 0
    roots[:, 0] = np.where(zero0, 0.0, np.where(crossing, s, np.where(zero1, 1.0, np.inf)))
    roots[:, 1] = np.where(zero0 & zero1, 1.0, np.inf)
    return roots, coef


def _earliest_hit(f, hit, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Earliest root of the cubic ``f(s)`` (sampled at 0, 1/3, 2/3, 1) at which ``hit(cand, s)`` holds.

    ``f(s)`` returns the (K,) values of K cubics in ``s``; ``hit(cand, s)`` says which candidates (indices)
    are in contact at their root ``s``. Returns the time of impact (inf if none) and the side before it.
    """
    samples = np.column_stack([f(s) for s in (0.0, 1 / 3, 2 / 3, 1.0)])
    return _first_hit(*_cubic_roots(samples), hit, k)


def _first_hit(roots: np.ndarray, coef: np.ndarray, hit, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The earliest of the ``roots`` (K, 3) of the polynomials ``coef`` at which ``hit(cand, s)`` holds: the time
    of impact (inf if none) and the side before it (:func:`_earliest_hit`)."""
    toi = np.full(k, np.inf)
    which = np.zeros(k, dtype=np.int64)
    for j in range(3):                      # the (at most three) roots in increasing order
        cand = np.flatnonzero(np.isfinite(roots[:, j]) & ~np.isfinite(toi))
        if not len(cand):
            continue
        s = roots[cand, j]
        ok = hit(cand, s)
        toi[cand[ok]] = s[ok]
        which[cand[ok]] = j
    return toi, _side_before(roots, coef, toi, which)


def point_triangle_toi(p0, p1, a0, a1, b0, b1, c0, c1, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Earliest ``s`` at which the moving point meets the moving triangle (inf if never), and its side.

    The side is the sign of ``f`` just before the hit (of ``f(0)`` without one):
    +1 if the point was on the side of the triangle's normal ``(b - a) x (c - a)``.

    Parameters
    ----------
    p0, p1, a0, a1, b0, b1, c0, c1 : (K, 3) arrays
        Start and end positions of the point and of the triangle's corners, m.
    tol : float
        A root of the coplanarity cubic is a hit if the point is within ``tol`` (m)
        of the triangle then.
    """
    def f(s):
        s = np.full(len(p0), s)
        a = _lerp(a0, a1, s)
        n = np.cross(_lerp(b0, b1, s) - a, _lerp(c0, c1, s) - a)
        return _dot(n, _lerp(p0, p1, s) - a)

    def hit(cand, s):
        p = _lerp(p0[cand], p1[cand], s)
        q, _ = point_triangle_closest(p, _lerp(a0[cand], a1[cand], s), _lerp(b0[cand], b1[cand], s),
                                      _lerp(c0[cand], c1[cand], s))
        return _dot(p - q, p - q) <= tol * tol

    if a0 is a1 and b0 is b1 and c0 is c1:      # a triangle that does not move (an obstacle's): f is linear
        n = np.cross(b0 - a0, c0 - a0)
        return _first_hit(*_linear_roots(_dot(n, p0 - a0), _dot(n, p1 - a0)), hit, len(p0))
    return _earliest_hit(f, hit, len(p0))


def edge_edge_toi(p0, p1, q0, q1, u0, u1, w0, w1, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Earliest ``s`` at which moving edge ``pq`` meets moving edge ``uw`` (inf if never), and its side.

    The side is the sign of ``f`` just before the hit (of ``f(0)`` without one).

    ``f(s) = ((q - p) x (w - u)) . (u - p)``; a root is a hit if the segments'
    closest points are within ``tol`` (m) then.
    """
    def f(s):
        s = np.full(len(p0), s)
        p = _lerp(p0, p1, s)
        u = _lerp(u0, u1, s)
        n = np.cross(_lerp(q0, q1, s) - p, _lerp(w0, w1, s) - u)
        return _dot(n, u - p)

    def hit(cand, s):
        p, q = _lerp(p0[cand], p1[cand], s), _lerp(q0[cand], q1[cand], s)
        u, w = _lerp(u0[cand], u1[cand], s), _lerp(w0[cand], w1[cand], s)
        a, b = segment_closest(p, q, u, w)
        gap = (p + a[:, None] * (q - p)) - (u + b[:, None] * (w - u))
        return _dot(gap, gap) <= tol * tol

    if u0 is u1 and w0 is w1:       # edge uw does not move (an obstacle's): f is quadratic, its coefficients exact
        e = np.cross(q0 - p0, w0 - u0)                  # (d0 + s dd) x e, with d = q - p and e = w - u
        de = np.cross((q1 - q0) - (p1 - p0), w0 - u0)
        g0, dp = u0 - p0, p1 - p0                       # u - p = g0 - s dp
        coef = np.zeros((len(p0), 4))
        coef[:, 0] = _dot(e, g0)
        coef[:, 1] = _dot(de, g0) - _dot(e, dp)
        coef[:, 2] = -_dot(de, dp)
        return _first_hit(*_poly_roots(coef), hit, len(p0))
    return _earliest_hit(f, hit, len(p0))
