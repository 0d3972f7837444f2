"""The collision guard's constants (units: metres), in one place; their measurements are cited
beside them."""
# Default clearance between the body and the innermost garment (DESIGN.md §3: 2–4 mm).
DEFAULT_MARGIN_M = 0.002
# Default clearance between consecutive garment layers (the pipeline's and the API's default too).
DEFAULT_LAYER_GAP_M = 0.003
# Candidates per garment vertex: the posed closest body vertex is among the 8 rest-pose
# nearest ones for ~96-99 % of vertices on random poses (0.3 rad per bone, measured).
DEFAULT_CANDIDATES = 8
# A candidate across a gap opposes the point's own surface by more than 120°.
_OPPOSING_COS = -0.5
# Skin-aware plans: points closer than this (rest pose) to a part skinned to another bone get
# per-frame nearest candidates, searched among the collider vertices within DYNAMIC_REGION_M.
DYNAMIC_RISK_M = 0.30
DYNAMIC_REGION_M = 0.05
# ... and among the farther collider vertices within DYNAMIC_REACH_M (a forearm that swings
# against the back, a hand against the thigh), thinned to one per DYNAMIC_VOXEL_M cell. On the
# validation clip 02_02 (a walk; `python tools/guard_reach_validation.py`, retarget T-shirt) they
# change nothing: the same inside % without them, at 2 cm and at 3 cm cells, neutral and heaviest
# (the plan's region grows from 1938 to 3046 vertices): no limb comes against the torso there, so
# validation neither justifies nor refutes them; they are kept for motions where one does, seen
# on 01_01 (a test clip, reported only: learned v2 models, heaviest adult 1.12 -> 0.61 % clean
# inside, +1.4-2 ms per garment-frame; docs/benchmarks.md).
DYNAMIC_REACH_M = 0.30
DYNAMIC_VOXEL_M = 0.02
# Per-frame nearest candidates per dynamic point.
DYNAMIC_K = 3
# Passes of the body guard (each re-picks the closest candidate: concave creases converge).
GUARD_ITERATIONS = 2
# Rest-pose candidates of a skin-aware plan (its per-frame search finds the posed nearest ones).
SKIN_PLAN_K = 4
# An across-the-gap candidate limits the push only while it is this close to the point, metres.
_SQUEEZE_RADIUS_M = 0.02
# A point behind the plane of a candidate within this tangential offset is inside that part ...
_TANGENT_M = 0.012
# ... if that candidate is at most this much farther than the nearest one, metres.
_FARTHER_M = 0.02
# Closed colliders: the one-ring triangles of this many nearest candidates decide, after the push,
# whether a point is still inside (``_refine_block``; 0 turns the check off). On the validation
# clip 02_02 (`python tools/guard_check_validation.py`, default T-shirt and jacket, arms lifted)
# the check leaves 2-4x fewer vertices inside than the push alone (heaviest adult: T-shirt 0.099
# -> 0.047 %, jacket 0.019 -> 0.005 %; neutral 0.013 -> 0.010 % and 0) for +1-8 ms per
# garment-frame; 5 candidates halve the rest again for +1-4 ms more, not taken: the default's
# exact repair moves what is left.
REFINE_CANDIDATES = 3
# Passes of that check; each later one revisits only the points the previous one moved (on 02_02
# the second changes the inside share by at most 0.001 points of %; it is cheap).
REFINE_PASSES = 2
# Extra candidates are looked up this far along the rest normal (the other side of a crease).
DEFAULT_AHEAD_M = 0.015
