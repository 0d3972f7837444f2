"""Collision guard: push garment vertices out of the posed body (and out of inner garments).

Thesis ch. 4.2.1 ("Collision postprocessing"): after skinning, cloth vertices that collide
with the body are pushed "outside their closest body primitive". Here the primitive is the
closest collider vertex with its area-weighted normal (its tangent plane), and the vertex is
pushed along that normal to a margin outside:

    c* = argmin_j |p - c_j|         over the candidates j of p           (closest primitive)
    s  = (p - c*) . n*               signed distance to the tangent plane at c*, metres
    p' = p + max(margin - s, 0) n*   (no-op for vertices already beyond the margin)

For a convex patch the tangent plane at c* supports the surface, so |p' - surface| >= margin;
in concave creases one pass can leave a vertex a little short of the margin (``iterations``
repeats the pass, with a fresh closest candidate each time).

Cost: the closest collider vertex is searched among ``k`` candidates per garment vertex, chosen
once per request by a KD-tree in the rest pose (``GuardPlan``); a frame then costs a few
gathers over (N, k) and normals for the plan's collider vertices only. Flat 1-D ``np.take``
on coordinate planes (structure of arrays) is several times faster than gathering (., 3) rows.
Points that another body part can reach when a joint bends (skin-aware plans) also get their
posed nearest collider vertices in every frame, from a KD-tree over the collider vertices near
them in the rest pose plus, thinned, the farther ones a limb can bring in (a forearm against
the back); this per-frame search is most of the guard's cost, the closest-triangle check
below the second largest part (measured for a 5k-vertex T-shirt: ~4 and 3-4 ms per frame).

Self-intersecting bodies. Under LBS the posed body intersects itself (an upper arm sunk into
the torso); a garment vertex squeezed there cannot be outside both parts. The guard does not
push it through the other part. ``GuardPlan.build`` marks, in the rest pose (where the body does
not intersect itself), the candidates c_j that lie on another surface across a gap: normal
opposing the point's own surface (n_j . n_0 < -0.5), the point on their outer side
((p - c_j) . n_j > 0) and ahead of it ((c_j - p) . n_0 > 0); it also adds candidates found
``ahead_m`` along the normal so that such a surface is seen. Per frame, each marked candidate
limits the push to the balanced position where p is equally far from (or equally deep in) both
planes,

    s*(delta) = s* + delta,  s_j(delta) = s_j + (n* . n_j) delta
    delta_j  = (s_j - s*) / (1 - n* . n_j)        (s*(delta_j) = s_j(delta_j))
    delta    = min(max(margin - s*, 0), max(min_j delta_j, 0)),

so a point in a gap narrower than two margins stops half-way, and a point inside both parts
stays where it is (the deeper of its two penetrations never grows). The far side of a thin part
(a finger) is not marked: in the rest pose the point is inside its plane. Parts that are
farther than ``ahead_m`` apart in the rest pose (the arm and the torso) are not seen; a garment
vertex there is pushed out of its own part only (it was inside the other already: the metric's
self-intersection exclusion covers it). ``frames=`` adds candidates from posed key frames.

Closest-triangle check (closed colliders: the body). The nearest vertex's tangent plane
misjudges points where the surface bends within a few millimetres of them (an elbow pit, an
armpit crease, the side of a concave fold): most of the garment vertices the plane push leaves
inside the body are of this kind. After the push, every point that the
screening kept is checked against the one-ring triangles of its ``REFINE_CANDIDATES`` nearest
candidates: q = the closest point on those triangles (``inference.triangles``), n_q = the
vertex normals interpolated at q (Phong), and a point with (p - q) . n_q < 0 moves to
q + margin n_q / |n_q|; a second pass re-checks the points the first one moved (one that lands
inside a neighbouring part). The plan therefore holds the candidates' one-rings
(``GuardPlan.ring``) and their corners. On the validation clip 02_02 it leaves 1.3-4x fewer
vertices inside than the push alone (``constants.REFINE_CANDIDATES``); what remains lies mostly in
the body's own folds and overlaps, where no local push can be right (the exact repair's job).

Layers (``guard_layers``): garments in layer order, innermost first; layer i is pushed out of
the body with margin ``body_margin_m + i * layer_gap_m`` and then out of every inner garment
j < i (already guarded) with margin ``layer_gap_m``, along the inner garment's outward
vertex normals. Open collider meshes (garments) have borders: a vertex whose closest collider
vertex lies on the border and which lies beyond it (tangential offset > the collider's median
edge length) is not pushed (it does not project onto the collider surface).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

# The package, by job: constants.py (every constant), push.py (the kernels), plan.py (GuardPlan),
# layers.py (guard, LayerPlans, guard_layers).
from inference.guard.constants import DEFAULT_CANDIDATES, DEFAULT_LAYER_GAP_M, DEFAULT_MARGIN_M, GUARD_ITERATIONS
from inference.guard.layers import LayerPlans, guard, guard_layers
from inference.guard.plan import GuardPlan, boundary_vertices
from inference.guard.push import push_outside

__all__ = ["DEFAULT_CANDIDATES", "DEFAULT_LAYER_GAP_M", "DEFAULT_MARGIN_M", "GUARD_ITERATIONS", "GuardPlan", "LayerPlans",
           "boundary_vertices", "guard", "guard_layers", "push_outside"]
