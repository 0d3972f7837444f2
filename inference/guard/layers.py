"""The guard of one garment against one collider (``guard``), and of a stack of garments against
the body and each other, innermost first (``LayerPlans``, ``guard_layers``; the algorithm:
``inference.guard``).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from inference.errors import InputShapeError, InputValueError
from inference.guard.constants import DEFAULT_CANDIDATES, DEFAULT_LAYER_GAP_M, DEFAULT_MARGIN_M, GUARD_ITERATIONS, SKIN_PLAN_K
from inference.guard.plan import GuardPlan, collider_topology
from inference.guard.push import _check_frames, _planes, _push_planes
from inference.mesh import content_key, major_components


def guard(
    points: np.ndarray,
    collider: np.ndarray,
    plan: GuardPlan,
    margin_m: float = DEFAULT_MARGIN_M,
    *,
    max_push_m: float | None = None,
    iterations: int = 1,
    check: bool = True,
) -> np.ndarray:
    """Collision guard, thesis ch. 4.2.1: no point inside or within ``margin_m`` of the collider.

    points   : (B, T, N, 3) float32, metres, posed garment vertices
    collider : (B, T, M, 3) float32, metres, posed body (or inner garment) vertices
    plan     : ``GuardPlan.build`` of these points and this collider
    check    : the closest-triangle check after the push (closed colliders; module docstring)
    returns  : (B, T, N, 3) float32, metres (``push_outside`` on the plan's collider vertices)
    """
    points = _check_frames("points", points)
    B, T, N, _ = points.shape
    if N != plan.candidates.shape[1] or plan.candidates.shape[0] not in (1, B):
        raise InputShapeError("points", f"({plan.candidates.shape[0]}, T, {plan.candidates.shape[1]}, 3)", points.shape)
    if np.shape(collider)[:2] != (B, T):
        raise InputShapeError("collider", f"({B}, {T}, M, 3)", np.shape(collider))
    cp, cn = plan.collider_planes(collider)
    out = _push_planes(
        _planes(points).reshape(3, B * T, N), cp, cn, plan.candidates, plan.across, T, len(plan.collider_ids), margin_m,
        max_push_m, plan.boundary, plan.reach_m, iterations, plan, check,
    )
    return np.moveaxis(out.reshape(3, B, T, N), 0, -1)


# Body plans kept per process for ``LayerPlans.build(reuse=)``: a shopper's body comes back with
# other motions and outfits, and a static garment's plan on it (built from its rest form) is the
# same; ~60 ms to build for the jacket on the anny body (docs/benchmarks.md, "Outfits: the guard's cost").
PLAN_CACHE_ENTRIES = 16
_PLANS: OrderedDict = OrderedDict()
_PLANS_LOCK = threading.Lock()


def _reused_body_plan(points: np.ndarray, body_rest: np.ndarray, body_faces: np.ndarray, k: int,
                      skin: tuple[np.ndarray, np.ndarray] | None, rings: bool) -> GuardPlan:
    """``GuardPlan.build`` of a garment's rest form against the body, kept (LRU, PLAN_CACHE_ENTRIES)
    under the contents of the points and the body's rest vertices and the identities of the faces
    and the skinning weights (model arrays, never changed in place; the entry holds them, so that
    their ids are not reused while it lives)."""
    held = (body_faces,) + (tuple(skin) if skin is not None else ())
    key = (content_key(points), content_key(body_rest), tuple(id(a) for a in held), k, rings)
    with _PLANS_LOCK:
        hit = _PLANS.get(key)
        if hit is not None:
            _PLANS.move_to_end(key)
            return hit[1]
    plan = GuardPlan.build(points, body_rest, body_faces, k, skin=skin, k_skin=2, rings=rings)
    with _PLANS_LOCK:
        _PLANS[key] = (held, plan)
        while len(_PLANS) > PLAN_CACHE_ENTRIES:
            _PLANS.popitem(last=False)
    return plan


@dataclass(frozen=True)
class LayerPlans:
    """Plans for a stack of garments, innermost first.

    body  : one ``GuardPlan`` per layer against the body
    inner : inner[i][j] is the plan of layer i against inner layer j < i
    """

    body: list[GuardPlan]
    inner: list[list[GuardPlan]]
    skin: np.ndarray | None = None  # (Vb,) bool: the body's major components (``inference.repair``)

    @classmethod
    def build(
        cls,
        layers_rest: Sequence[np.ndarray],
        layer_faces: Sequence[np.ndarray],
        body_rest: np.ndarray,
        body_faces: np.ndarray,
        k: int = DEFAULT_CANDIDATES,
        layer_weights: Sequence[np.ndarray] | None = None,
        body_weights: np.ndarray | None = None,
        rings: bool = True,
        between_layers: bool = True,
        reuse: Sequence[bool] | None = None,
    ) -> "LayerPlans":
        """layers_rest : each (B, N_i, 3) rest garment vertices; layer_faces : each (F_i, 3);
        layer_weights / body_weights : optional LBS weights (N_i, J) / (Vb, J) for
        skinning-aware body candidates (GuardPlan.build's ``skin``); rings : the body plans keep
        the triangles of the closest-triangle check (not needed with ``guard_layers(check=False)``);
        between_layers : the plans of each layer against the inner ones (False: the layers are
        guarded against the body only, and ``inference.layers`` orders them); reuse : per layer,
        whether its body plan may come from (and go to) the process's plans of earlier requests (a
        garment whose rest form does not follow the motion: the same rest form and body give the
        same plan; default none)."""
        if len(layers_rest) != len(layer_faces):
            raise InputValueError("layer_faces", f"expected {len(layers_rest)} face arrays, got {len(layer_faces)}")
        reuse = [False] * len(layers_rest) if reuse is None else list(reuse)
        if len(reuse) != len(layers_rest):
            raise InputValueError("reuse", f"expected {len(layers_rest)} flags, got {len(reuse)}")
        body = []
        for i, g in enumerate(layers_rest):
            kk, skin = (k, None) if layer_weights is None else (SKIN_PLAN_K, (layer_weights[i], body_weights))
            if reuse[i]:
                body.append(_reused_body_plan(g, body_rest, body_faces, kk, skin, rings))
            else:
                body.append(GuardPlan.build(g, body_rest, body_faces, kk, skin=skin, k_skin=2, rings=rings))
        inner = [[GuardPlan.build(layers_rest[i], layers_rest[j], layer_faces[j], k) for j in range(i)] if between_layers else []
                 for i in range(len(layers_rest))]
        Vb = np.shape(body_rest)[-2]
        _, boundary, usable = collider_topology(body_faces, Vb)
        skin = np.zeros(Vb, bool)
        skin[usable] = True  # the body's major components (closed: no boundary)
        return cls(body=body, inner=inner, skin=skin if not boundary.any() else major_components(body_faces, Vb))


def guard_layers(
    layers: Sequence[np.ndarray],
    body: np.ndarray,
    plans: LayerPlans,
    body_margin_m: float = DEFAULT_MARGIN_M,
    layer_gap_m: float = DEFAULT_LAYER_GAP_M,
    check: bool = True,
) -> list[np.ndarray]:
    """Guard a stack of garments, innermost first (see the module docstring).

    layer i: p_i <- guard(p_i, body, margin = body_margin_m + i * layer_gap_m)
             p_i <- guard(p_i, p_j, margin = layer_gap_m) for j = 0 .. i-1 (guarded p_j)
    layers : each (B, T, N_i, 3) float32, metres ; body : (B, T, Vb, 3) float32, metres
    check  : the closest-triangle check against the body (module docstring; compiled, ~1.7 ms per
             garment-frame of leggings + shorts, ~3.5k vertices each; 5.1 in numpy)
    returns: list of (B, T, N_i, 3) float32
    """
    if len(layers) != len(plans.body):
        raise InputValueError("layers", f"expected {len(plans.body)} layers, got {len(layers)}")
    out: list[np.ndarray] = []
    for i, p in enumerate(layers):
        p = guard(p, body, plans.body[i], body_margin_m + i * layer_gap_m, iterations=GUARD_ITERATIONS, check=check)
        for j in range(len(plans.inner[i])):  # none when the plans were built without between_layers
            p = guard(p, out[j], plans.inner[i][j], layer_gap_m)
        out.append(p)
    return out
