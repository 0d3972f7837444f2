"""Contacts of the garment with the body: which body vertices' tangent planes each garment
vertex collides with, and the collision term of eq. 5.12 against them.

d(x) of eq. 5.12 from SNUG's closest body vertex jumps when that vertex changes (neighbouring
tangent planes differ), which stalls line searches; ``Collider`` blends the tangent planes of
each vertex's candidates instead (``SolverSettings.contact_smoothing_m``, 4 mm; the
closest-vertex form is the limit and remains available, with contact rounds re-selecting the
closest vertex between solver runs). On the anny body the candidates are chosen once in the rest
pose among body vertices skinned like the garment vertex (``RestPoseContacts``), and garment
vertices near the posed body's LBS self-intersections do not collide
(``SolverSettings.exclusion_radius_m``): a sleeve squeezed between an arm sunk into the torso
and the torso cannot be outside both, and its opposing contacts stalled the solver (measured).
``Contacts`` are the planes one solver run holds fixed.

Units: metres (positions, distances), joules (energies), J/m^2 (Hessians).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from inference.mesh import vertex_normals
from inference.metrics import self_intersecting_vertices
from training.physics import ClothGeometry, closest_body_vertices, collision_energy, collision_hessian


class RestPoseContacts:
    """Contact candidates chosen once in the rest pose, among body vertices that move like the
    garment vertex (in the spirit of the collision guard's rest-pose plans, ``inference.guard``).

    Under LBS the posed body intersects itself (an upper arm sunk into the torso, DESIGN.md §5)
    and squeezes the garment between the two: a sleeve vertex under the arm whose closest posed
    body vertex lies on the torso gets contact planes on both sides, and the solver stalls
    there (measured on the T-shirt lowering the arms from the A-pose: residual forces of
    hundreds of vertex weights, line-search steps of 1/64). So the candidates of garment vertex
    v are its ``k`` nearest rest-pose body vertices j whose skinning weights resemble its own,
    cos(w_v, w_j) >= ``min_similarity`` (a sleeve collides with the arm, the torso panel with
    the torso), with both in the rest pose (the garment's rest drape on the shaped rest body);
    its contact in a posed frame is the closest of them (or their blend). Collisions with parts
    that move otherwise (a sleeve against the torso) are not seen — the garment has no self-
    collision either (SNUG) — and a vertex sliding farther than its candidates reach (k = 16:
    ~2-3 cm on anny) keeps colliding with the last of them. (Mapping vertices back to the rest
    pose per step through the inverse of their blended skinning transform was tried: near the
    shoulders that transform is nearly singular and sent candidates metres away.)

    rest_garment : (V, 3) metres, the garment on the shaped body in the rest pose
    rest_body    : (M, 3) metres, the shaped body in the rest pose
    garment_weights : (V, J), body_weights : (M, J) skinning weights (same bones)
    k            : candidates per vertex ; min_similarity : cosine of the weight vectors
    """

    def __init__(self, rest_garment: np.ndarray, rest_body: np.ndarray, garment_weights: np.ndarray | None = None, body_weights: np.ndarray | None = None, k: int = 16, min_similarity: float = 0.3, pool: int = 96):
        rest_garment = np.asarray(rest_garment, np.float64)
        k = min(k, len(rest_body))
        _, near = cKDTree(np.asarray(rest_body, np.float64)).query(rest_garment, k=min(pool, len(rest_body)))
        near = near.reshape(len(rest_garment), -1)  # (V, pool), nearest first
        if garment_weights is None or body_weights is None:
            self.candidates = near[:, :k]
            return
        wg = garment_weights / np.linalg.norm(garment_weights, axis=1, keepdims=True)
        wb = body_weights / np.linalg.norm(body_weights, axis=1, keepdims=True)
        similar = np.einsum("vj,vpj->vp", wg, wb[near]) >= min_similarity  # (V, pool)
        # the k nearest similar ones, in distance order; vertices with fewer keep their nearest
        order = np.argsort(~similar, axis=1, kind="stable")[:, :k]
        chosen = np.take_along_axis(near, order, axis=1)
        few = similar.sum(1) < k
        chosen[few] = near[few, :k]
        self.candidates = chosen
        self.unmatched = int(few.sum())

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """(V, k) body vertex ids (the same for every pose)."""
        return self.candidates


class Contacts(NamedTuple):
    """Contact planes of one solver run: index (1, V, 1) int64, the body vertex whose tangent
    plane each garment vertex collides with; active (1, V) bool, False for vertices left out."""

    index: torch.Tensor
    active: torch.Tensor

    def changed(self, other: "Contacts") -> int:
        return int(((self.index != other.index)[..., 0] | (self.active != other.active)).sum())


class Collider:
    """A posed body for one solve: vertices and unit normals (tensors) and how contacts are chosen.

    points     : (M, 3) metres ; faces : (Fb, 3) ; normals from ``inference.guard.vertex_normals``
    candidates : optional x (V, 3) -> (V, k) body ids (``RestPoseContacts``); default: the
                 ``k`` nearest posed body vertices (KD-tree) at each contact selection
    smoothing_m: blend the candidates' tangent planes (``physics.body_signed_distances``);
                 None: SNUG's closest vertex
    exclusion_radius_m : garment vertices closer than this to a skin vertex inside another body
                 part (``inference.metrics.self_intersecting_vertices``: the posed body's LBS
                 self-intersections) do not collide. The skin is no surface there: a garment
                 vertex squeezed between an upper arm and the torso cannot be outside both,
                 and its opposing contact forces (measured: up to 800 x its weight on the
                 T-shirt at the armpits, walk frame 0) stall the solver. The same region is
                 left out of the collision metric (DESIGN.md §5, radius 2 cm). None: keep all.
    """

    def __init__(self, points: np.ndarray, faces: np.ndarray, dtype: torch.dtype, candidates: Callable[[np.ndarray], np.ndarray] | None = None, exclusion_radius_m: float | None = None, smoothing_m: float | None = None, k: int = 8):
        points = np.asarray(points, np.float64)
        self.smoothing_m, self._k = smoothing_m, min(k, len(points))
        self.points = torch.as_tensor(points[None], dtype=dtype)
        self.normals = torch.as_tensor(vertex_normals(points.astype(np.float32), faces)[None], dtype=dtype)
        self._candidates = candidates
        self._tree = cKDTree(points) if candidates is None else None
        self._exclusion = None
        self._radius = exclusion_radius_m
        self._active = None
        if exclusion_radius_m is not None:
            inside = self_intersecting_vertices(points[None].astype(np.float32), faces)[0]
            if inside.any():
                self._exclusion = cKDTree(points[inside])

    def contacts(self, x: torch.Tensor) -> Contacts:
        """The contact body vertices of every garment vertex and whether it collides: the closest
        one (1, V, 1), or with ``smoothing_m`` all its candidates (1, V, k), blended. Which
        vertices collide is decided at the first call (the solve's start) and kept: letting it
        change between contact rounds made the energy jump (measured)."""
        xs = x[0].detach().numpy()
        if self._candidates is None:
            k = self._k if self.smoothing_m is not None else 1
            index = torch.as_tensor(self._tree.query(xs, k=k)[1].reshape(1, len(xs), k), dtype=torch.int64)
        else:
            index = torch.as_tensor(self._candidates(xs)[None], dtype=torch.int64)
            if self.smoothing_m is None:
                index = closest_body_vertices(x.detach(), self.points, index)[..., None]
        if self._active is None:
            active = np.ones(len(xs), bool)
            if self._exclusion is not None:
                d, _ = self._exclusion.query(xs, k=1, distance_upper_bound=self._radius)
                active = d > self._radius
            self._active = torch.as_tensor(active[None])
        return Contacts(index, self._active)

    def collision(self, cloth: ClothGeometry, x: torch.Tensor, contacts: Contacts) -> torch.Tensor:
        """Eq. 5.12 against the tangent planes of the given contacts, (B,) J."""
        return collision_energy(cloth, x, self.points, self.normals, contacts.index, contacts.active, self.smoothing_m)

    def hessian(self, cloth: ClothGeometry, x: torch.Tensor, contacts: Contacts) -> torch.Tensor:
        """Per-vertex (1, V, 3, 3) Hessian of ``collision``."""
        return collision_hessian(cloth, x, self.points, self.normals, contacts.index, contacts.active, self.smoothing_m)
