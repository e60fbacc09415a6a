"""Collisions of the cloth with rigid obstacles: contacts as constraints of the implicit solve.

Imported only by a scene with ``[[obstacles]]``. An implicit step
(:meth:`Collider.step`) treats contact in the solve itself:

1. **Solve with the contacts carried from the last step.** A contact holds one
   vertex on a plane fixed in an obstacle's frame, ``n . x(t + h) = offset``: the
   tangent plane of the surface inflated by the thickness at the vertex's nearest
   point (or a feature contact's plane); the integrator turns it into a
   prescribed normal velocity through its own position update
   (:mod:`implicit_cloth.constraints`), the tangential motion free or held by
   friction.
2. **Detect** what the proposed step violates (:mod:`~implicit_cloth.collision.contacts`:
   vertex sweeps, mesh faces through the broad phase (:mod:`~implicit_cloth.collision.broadphase`), obstacle corners
   and edges against cloth triangles and edges, edge interiors against curved
   surfaces), **constrain** the vertices found and **solve again** from the same
   state (warm-started), so that an impact reaches the neighbours in the same
   step instead of kinking the cloth at the edge of the contact region.
3. **Friction** (:mod:`~implicit_cloth.collision.friction`): Coulomb's law in the
   solve, a sticking contact held in three directions, a sliding one with the
   kinetic force; a contact that pulls its vertex towards the obstacle is released.
4. **After the solves**: contacts leave inelastically (restitution as set),
   strain limiting keeps the contact planes, and the geometric response
   (:mod:`~implicit_cloth.collision.fallback`, Bridson, Fedkiw & Anderson 2002)
   corrects what the solves left; what it corrects is counted.

The obstacles' work is their contact impulses times their velocity at the
contact: zero for an obstacle that does not move, so the energy balance of
every step (:mod:`implicit_cloth.diagnostics`) has nothing to excuse a contact
treatment that creates energy. Explicit methods get the geometric response only.
Pinned vertices are never moved.
"""

from __future__ import annotations

from .collider import Collider
from .context import CollisionInfo, Context, Obstacle, cloth_edges

__all__ = ["Collider", "CollisionInfo", "Context", "Obstacle", "cloth_edges"]
