"""Collision response: inelastic impulses with Coulomb friction, and their distribution to vertices.

Velocity response at one contact (Bridson, Fedkiw & Anderson 2002, §7.2), with
``u`` the obstacle's velocity at the contact point and ``n`` the outward unit
normal: the relative velocity ``v_r = v - u`` splits into ``v_n = v_r . n`` and
``v_t = v_r - v_n n``. An approaching contact (``v_n < 0``) gets
``v_n' = -e v_n`` (``e`` = restitution), a change ``dv_n = v_n' - v_n >= 0``
(plus any normal impulse per unit mass the contact constraint applied in the
solve). Coulomb friction with coefficient ``mu``:

    v_t' = max(0, 1 - mu dv_n / |v_t|) v_t

which stops the sliding (static friction) when ``|v_t| <= mu dv_n`` and
otherwise removes ``mu dv_n`` of it (kinetic friction).

A correction ``D`` (a position or velocity change, m or m/s) of a point
``sum_i w_i x_i`` of a triangle or edge is shared among its vertices as
``d_i = w_i D / (m_i sum_j w_j^2 / m_j)``: the point moves by exactly ``D``
and a pinned vertex (``1/m = 0``) does not move at all. Where several
corrections touch a vertex in one pass they are averaged (a Jacobi pass); the
outer iteration converges to satisfy them all.
"""

from __future__ import annotations

import numpy as np

#: Corrections below this fraction of the thickness do not call for another response round.
SETTLE_FRACTION = 0.02
#: A vertex nearer than the thickness by less than this fraction of it is not pushed (one the solve held on
#: its contact plane ends there to round-off).
PROXIMITY_SLACK = 1e-6


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def impulse(v: np.ndarray, u: np.ndarray, n: np.ndarray, mu: np.ndarray | float, restitution: float,
            extra_dvn: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """New velocities (K, 3) m/s after an inelastic contact with friction, and the normal change dv_n (K,) m/s.

    Parameters
    ----------
    v, u, n : (K, 3) arrays
        Cloth velocity, obstacle velocity at the contact and outward unit normal.
    mu : float or (K,) array
        Coulomb friction coefficient.
    restitution : float
        ``e`` in [0, 1]: the approaching normal velocity is reversed and scaled by ``e``.
    extra_dvn : float or (K,) array
        Normal impulse per unit mass, m/s, already applied (by a contact constraint in
        the solve); it adds to the friction bound.
    """
    vr = v - u
    vn = _dot(vr, n)
    vt = vr - vn[:, None] * n
    vn_new = np.where(vn < 0, -restitution * vn, vn)
    dvn = (vn_new - vn) + np.maximum(extra_dvn, 0.0)
    vt_norm = np.sqrt(_dot(vt, vt))
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = np.where(vt_norm > 0, np.maximum(0.0, 1.0 - mu * dvn / vt_norm), 0.0)
    return u + vn_new[:, None] * n + keep[:, None] * vt, dvn


def spread(n_vertices: int, idx: np.ndarray, w: np.ndarray, inv_mass: np.ndarray,
           delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Share point corrections among the vertices of their triangles or edges (averaged per vertex).

    Parameters
    ----------
    idx : (K, m) int array
        Vertices of each primitive (m = 1, 2 or 3).
    w : (K, m) array
        Barycentric weights of the corrected point.
    inv_mass : (N,) array
        Inverse vertex masses, 0 for pinned vertices.
    delta : (K, 3) array
        Correction of each point.

    Returns
    -------
    change : (N, 3) array
        The averaged change of every vertex.
    touched : (N,) bool array
        Vertices that received a non-zero share.
    """
    im = inv_mass[idx] * w                                   # (K, m)
    den = np.einsum("km,km->k", w, im)
    ok = den > 0
    share = np.zeros(idx.shape + (3,))
    share[ok] = im[ok, :, None] * delta[ok, None, :] / den[ok, None, None]
    total = np.zeros((n_vertices, 3))
    count = np.zeros(n_vertices)
    moved = im > 0
    np.add.at(total, idx[moved], share[moved])
    np.add.at(count, idx[moved], 1.0)
    touched = count > 0
    total[touched] /= count[touched, None]
    return total, touched
