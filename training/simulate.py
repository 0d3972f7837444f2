"""Physics reference: implicit backward-Euler cloth simulation by energy minimisation.

Each time step solves eq. 5.4 (the minimisation form of backward Euler, eq. 5.3):

    x^{t+1} = argmin_x  L_inertia(x; x^t, v^t, dt) + L_static(x; posed body at t+1)

with exactly the energies the learned models are trained on (``training.physics``: eq. 5.6-5.12),
then v^{t+1} = (x^{t+1} - x^t) / dt. Every solve is logged (``SolveLog``: iterations, energy
before and after, gradient norm, largest per-vertex residual force, wall and CPU time) so the
reference can be judged by how well it converged, not trusted blindly.

Solver. Newton by default: the Hessians of ``training.physics`` (exact StVK while the system
matrix is positive definite, else with the stress clamped to its PSD part; bending
Gauss-Newton; collision and mass blocks) assembled into a sparse matrix, solved by sparse LU
(reused as the CG preconditioner of the following iterations), Armijo backtracking; stops on
the force tolerance, on a negligible energy decrease, or after ``max_iterations``. L-BFGS
(torch.optim.LBFGS, strong-Wolfe) is kept as ``method="lbfgs"``, but cloth is stiff: with the
SNUG material k dt^2 / m ~ E dt^2 / (rho A) ~ 1e3 on the catalog meshes, and L-BFGS did not
reach the tolerance in 200 iterations even on a 49-vertex free-falling square, where Newton
takes one iteration (measured).

Contacts (``Collider``, ``RestPoseContacts``). d(x) of eq. 5.12 from SNUG's closest body
vertex jumps when that vertex changes (neighbouring tangent planes differ), which stalls line
searches; the solver blends the tangent planes of each vertex's candidates instead
(``contact_smoothing_m``, 4 mm; the closest-vertex form is the limit and remains available,
with contact rounds re-selecting the closest vertex between solver runs). On the anny body the
candidates are chosen once in the rest pose among body vertices skinned like the garment
vertex, and garment vertices near the posed body's LBS self-intersections do not collide
(``exclusion_radius_m``): a sleeve squeezed between an arm sunk into the torso and the torso
cannot be outside both, and its opposing contacts stalled the solver (measured).

- ``settle``: static equilibrium against a fixed body. A garment held only by frictionless
  contact is not a well-posed static problem from an arbitrary start (it may slide, and the pure
  static energy has near-zero-stiffness modes, a singular Hessian), so it runs a damped dynamic
  settle: implicit steps with the velocity reset to zero after each step, i.e. proximal-point
  iterations x_{k+1} = argmin E_static(x) + 1/(2 h^2) |x - x_k|^2_M, which decrease E_static
  and stop when the static residual |dE_static/dx| is below the tolerance (then the proximal
  term's force M (x_{k+1} - x_k)/h^2 is too). Nothing is pinned: the garment rests on the body
  through the collision term (a T-shirt on the shoulders, trousers on the hips).
- ``quasi_static_drape``: ``settle`` of the ``.mhclo`` retarget fit on the shaped body in the
  rest pose.
- ``simulate``: dynamics against a moving collider given per frame (T, M, 3); the collider is
  interpolated linearly for substeps, with vertex normals rebuilt per substep; warm start =
  previous positions moved by the garment's skinning displacement (when given) or by the
  previous velocity.
- ``simulate_sequence``: on the anny body along a motion: a lead-in from the rest pose (where
  the drape is) to the clip's first pose, then the clip's frames.

CLI: ``python -m training.simulate --garment tshirt --clip walk --frames 60
--out build/reference/tshirt_walk.npz`` writes the sequence and the convergence log.

Units: metres, seconds, kg, newtons (gradients), joules (energies). Arrays float32 numpy at the
interface, float64 torch inside by default (``SolverSettings.dtype``).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from scipy.spatial import cKDTree

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, linear_blend_skinning
from inference.mesh import vertex_normals
from inference.metrics import self_intersecting_vertices
from training.protocol import lead_in_motion
from training.physics import (
    GRAVITY_M_S2,
    ClothGeometry,
    bending_hessian,
    body_candidates,
    closest_body_vertices,
    collision_energy,
    collision_hessian,
    energy_terms,
    inertia_energy,
    static_energy,
    strain_hessian,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SolverSettings:
    """Solver hyper-parameters of the physics reference (one place, saved with the outputs).

    method           : "newton" (default: projected Newton, sparse direct solves, backtracking
                       line search) or "lbfgs" (torch.optim.LBFGS, strong-Wolfe line search).
                       Cloth is stiff in-plane: k dt^2 / m = E dt^2 / (rho A) ~ 1e3 for the
                       catalog meshes at 60 Hz, and L-BFGS needs hundreds of iterations where
                       Newton needs a handful (measured, module notes).
    dtype            : "float64" (default; line searches on energies of ~1 J resolving ~1e-9 J
                       changes) or "float32"
    max_iterations   : iterations per solve (Newton or L-BFGS)
    history_size     : L-BFGS memory
    force_tolerance  : converged when every gradient entry |dE/dx_vc| <= force_tolerance x the
                       mean vertex weight m g (N). A residual force r moves a vertex by about
                       r dt^2 / m: 0.1 m g at dt = 1/60 s is 0.3 mm.
    energy_tolerance_m: Newton also stops when an iteration lowers the energy by less than the
                       garment's weight times this height (J; 1e-8 m: ~1e-8 J for a T-shirt).
                       In buckled regions the max-norm force criterion converges linearly long
                       after the energy has (measured on the T-shirt: 6 iterations to reach
                       1e-8 J, 30 without meeting 0.1 m g)
    candidates       : body candidates per garment vertex (``RestPoseContacts``; the per-frame collision metric)
    contact_rounds   : solves per step with the contact planes re-selected in between (``solve_step``)
    exclusion_radius_m: no collision for garment vertices this close to the posed body's
                       self-intersections (``Collider``); None: collide everywhere
    contact_smoothing_m: soft-min blend of the candidates' tangent planes in d(x) of eq. 5.12
                       (``physics.body_signed_distances``); None: SNUG's closest body vertex,
                       whose plane jumps between neighbours (the solver then needs contact
                       rounds and stalled where the garment is squeezed, measured)
    settle_dt_s      : proximal step h of the damped settle, seconds
    settle_steps     : most proximal steps of ``settle``
    """

    method: str = "newton"
    dtype: str = "float64"
    max_iterations: int = 30
    history_size: int = 20
    force_tolerance: float = 0.1
    energy_tolerance_m: float = 1e-8
    candidates: int = 16
    contact_rounds: int = 2
    exclusion_radius_m: float | None = 0.02
    contact_smoothing_m: float | None = 0.004
    settle_dt_s: float = 0.05
    settle_steps: int = 60

    def __post_init__(self):
        if self.method not in ("newton", "lbfgs"):
            raise ValueError(f"method: expected 'newton' or 'lbfgs', got {self.method!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype: expected 'float32' or 'float64', got {self.dtype!r}")
        for name in ("max_iterations", "history_size", "candidates", "contact_rounds"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.settle_steps < 0 or not self.force_tolerance > 0 or not self.settle_dt_s > 0:
            raise ValueError("settle_steps >= 0, force_tolerance > 0 and settle_dt_s > 0 expected")

    @property
    def torch_dtype(self) -> torch.dtype:
        return getattr(torch, self.dtype)


@dataclass(frozen=True)
class SolveLog:
    """One energy minimisation.

    kind              : "dynamic" (eq. 5.4), "settle" (proximal step) or "static"
    frame, substep    : where in the sequence (settle steps: substep = step index)
    iterations        : solver iterations (all contact rounds) ; evaluations : energy evaluations
    energy_start_j    : objective at the warm start ; energy_end_j : at the solution
    grad_norm_start_n : |dE/dx| (L2 over all coordinates, N) at the warm start ; grad_norm_end_n at the solution
    max_force_n       : largest per-vertex |dE/dx_v| at the solution, N
    tolerance_n       : per-coordinate gradient tolerance, N ; converged : max |dE/dx_vc| <= tolerance_n
    stop              : why the (last) solver run stopped: "force" (tolerance met), "energy" (an
                        iteration gained less than ``energy_tolerance_m`` x weight), "line_search",
                        "iterations" (``max_iterations``)
    last_step_m       : largest vertex displacement of the last Newton step, metres (an
                        estimate of the remaining position error; NaN for L-BFGS)
    seconds           : wall time
    """

    kind: str
    frame: int
    substep: int
    iterations: int
    evaluations: int
    energy_start_j: float
    energy_end_j: float
    grad_norm_start_n: float
    grad_norm_end_n: float
    max_force_n: float
    tolerance_n: float
    converged: bool
    stop: str
    last_step_m: float
    seconds: float
    cpu_seconds: float


@dataclass
class SimulationLog:
    """Convergence of a run: every solve, plus per output frame the energy terms (J) and time (s).

    frame_energies: strain, bending, gravity, collision (posed body of the frame; SNUG's closest
    body vertex among the ``candidates`` nearest, every vertex colliding) and inertia
    (eq. 5.6 over the output frames, dt = 1/fps; 0 for the first two frames), each (T,).
    """

    solves: list[SolveLog] = field(default_factory=list)
    frame_energies: dict[str, np.ndarray] = field(default_factory=dict)
    frame_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_cpu_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def arrays(self, prefix: str = "log_") -> dict[str, np.ndarray]:
        """Flat arrays for an ``.npz``: one (N,) column per ``SolveLog`` field, (T,) per energy."""
        out = {}
        for name in SolveLog.__dataclass_fields__:
            values = [getattr(s, name) for s in self.solves]
            out[prefix + name] = np.array(values, dtype=np.str_ if name in ("kind", "stop") else (bool if name == "converged" else np.float64))
        for k, v in self.frame_energies.items():
            out[f"energy_{k}_j"] = np.asarray(v, np.float64)
        out["frame_seconds"] = np.asarray(self.frame_seconds, np.float64)
        out["frame_cpu_seconds"] = np.asarray(self.frame_cpu_seconds, np.float64)
        return out

    def summary(self, kind: str = "dynamic") -> dict:
        """Means / maxima over the solves of one kind (for logs and the final report)."""
        s = [x for x in self.solves if x.kind == kind]
        if not s:
            return {"solves": 0}
        it = np.array([x.iterations for x in s])
        g = np.array([x.grad_norm_end_n for x in s])
        f = np.array([x.max_force_n for x in s])
        return {
            "solves": len(s),
            "iterations_mean": float(it.mean()),
            "iterations_max": int(it.max()),
            "evaluations_mean": float(np.mean([x.evaluations for x in s])),
            "grad_norm_end_n_median": float(np.median(g)),
            "grad_norm_end_n_max": float(g.max()),
            "max_force_n_max": float(f.max()),
            "max_force_n_median": float(np.median(f)),
            "last_step_m_median": float(np.median([x.last_step_m for x in s])),
            "last_step_m_max": float(np.max([x.last_step_m for x in s])),
            "converged_fraction": float(np.mean([x.converged for x in s])),
            "stops": {k: int(sum(x.stop == k for x in s)) for k in ("force", "energy", "line_search", "iterations")},
            "seconds_per_solve": float(np.mean([x.seconds for x in s])),
            "cpu_seconds_per_solve": float(np.mean([x.cpu_seconds for x in s])),
            "energy_decreased_fraction": float(np.mean([x.energy_end_j <= x.energy_start_j for x in s])),
        }


# ------------------------------------------------------------------------------ solver
def _value_and_grad(energy: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Summed energy (J) and its gradient (N) at x (1, V, 3)."""
    y = x.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        e = energy(y).sum()
        (g,) = torch.autograd.grad(e, y)
    return e.detach(), g


def minimize_energy(energy: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor, tolerance_n: float, max_iterations: int = 200, history_size: int = 20) -> tuple[torch.Tensor, dict]:
    """Minimise a scalar energy (J) of positions (1, V, 3) metres by L-BFGS with strong-Wolfe line search.

    Stops when every gradient entry is <= tolerance_n (N), after ``max_iterations`` iterations,
    or when the line search makes no progress. Returns the minimiser (detached) and a report:
    iterations, evaluations, energy_start_j, energy_end_j, grad_norm_start_n, grad_norm_end_n,
    max_force_n, tolerance_n, converged, seconds.
    """
    t0 = time.perf_counter()
    x = x0.detach().clone().requires_grad_(True)
    e0, g0 = _value_and_grad(energy, x)
    opt = torch.optim.LBFGS(
        [x],
        lr=1.0,
        max_iter=max_iterations,
        max_eval=4 * max_iterations,
        history_size=history_size,
        tolerance_grad=tolerance_n,
        tolerance_change=1e-15,
        line_search_fn="strong_wolfe",
    )

    def closure():
        opt.zero_grad()
        e = energy(x).sum()
        e.backward()
        return e

    opt.step(closure)
    state = opt.state[x]
    x_end = x.detach()
    e1, g1 = _value_and_grad(energy, x_end)
    report = {
        "iterations": int(state.get("n_iter", 0)),
        "evaluations": int(state.get("func_evals", 0)) + 2,
        "energy_start_j": float(e0),
        "energy_end_j": float(e1),
        "grad_norm_start_n": float(g0.norm()),
        "grad_norm_end_n": float(g1.norm()),
        "max_force_n": float(g1.norm(dim=-1).max()),
        "tolerance_n": float(tolerance_n),
        "converged": bool(g1.abs().max() <= tolerance_n),
        "seconds": time.perf_counter() - t0,
    }
    if not report["energy_end_j"] <= report["energy_start_j"]:  # strong-Wolfe steps only decrease it
        log.warning("energy rose during a solve: %.6g -> %.6g J", report["energy_start_j"], report["energy_end_j"])
    return x_end, report


def tolerance_newtons(cloth: ClothGeometry, settings: SolverSettings) -> float:
    """Per-coordinate gradient tolerance: force_tolerance x mean vertex weight (N)."""
    return settings.force_tolerance * cloth.total_mass_kg / cloth.num_vertices * GRAVITY_M_S2


class HessianAssembly:
    """Sparse (3V x 3V) CSR assembly of per-element Hessian blocks of one garment.

    The sparsity pattern (triangles: 9 x 9 blocks, hinges: 12 x 12, vertices: 3 x 3) is built
    once; ``matrix`` then sums block entries into it with one ``np.bincount``.
    """

    def __init__(self, cloth: ClothGeometry):
        V = cloth.num_vertices
        self.size = 3 * V

        def dofs(elements):  # (n, k) vertex ids -> (n, 3k) dof ids, ordered (corner, coordinate)
            return (3 * elements[:, :, None] + np.arange(3)).reshape(len(elements), -1)

        blocks = [dofs(cloth.faces.numpy()), dofs(cloth.hinges.numpy()), dofs(np.arange(V)[:, None])]
        keys = np.concatenate([(d[:, :, None] * self.size + d[:, None, :]).ravel() for d in blocks])
        unique, self._position = np.unique(keys, return_inverse=True)
        self._indices = (unique % self.size).astype(np.int32)
        self._indptr = np.searchsorted(unique // self.size, np.arange(self.size + 1)).astype(np.int32)

    def matrix(self, triangle_blocks: np.ndarray, hinge_blocks: np.ndarray, vertex_blocks: np.ndarray) -> sp.csr_matrix:
        """triangle_blocks (F, 9, 9), hinge_blocks (H, 12, 12), vertex_blocks (V, 3, 3) -> (3V, 3V) CSR."""
        values = np.concatenate([triangle_blocks.ravel(), hinge_blocks.ravel(), vertex_blocks.ravel()])
        data = np.bincount(self._position, weights=values, minlength=len(self._indices))
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(self.size, self.size))


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


class StepProblem:
    """The objective of one implicit step, eq. 5.4: inertia (optional) + strain + bending + gravity
    + collision against one posed body (optional), with its gradient and PSD Hessian.

    inertia : (x_prev, x_prev2, dt_s) of eq. 5.6, or None ; body : Collider or None
    """

    def __init__(self, cloth: ClothGeometry, assembly: HessianAssembly | None, inertia: tuple[torch.Tensor, torch.Tensor, float] | None, body: Collider | None):
        self.cloth, self.assembly, self.inertia, self.body = cloth, assembly, inertia, body

    def energy(self, x: torch.Tensor, contacts: Contacts | None) -> torch.Tensor:
        e = static_energy(self.cloth, x)  # strain + bending + gravity (eq. 5.7 without collision)
        if self.inertia is not None:
            e = e + inertia_energy(self.cloth, x, *self.inertia)
        if self.body is not None:
            e = e + self.body.collision(self.cloth, x, contacts)
        return e

    def static(self, x: torch.Tensor, contacts: Contacts | None) -> torch.Tensor:
        """L_static only (eq. 5.7): the residual of static equilibrium is its gradient."""
        e = static_energy(self.cloth, x)
        return e + self.body.collision(self.cloth, x, contacts) if self.body is not None else e

    def hessian(self, x: torch.Tensor, contacts: Contacts | None, project: bool = True) -> sp.csr_matrix:
        """Hessian of ``energy`` (physics.*_hessian), (3V, 3V) CSR, J/m^2: PSD approximation, or
        with project=False the exact strain Hessian (indefinite where compression outweighs the
        mass and bending terms)."""
        cloth = self.cloth
        with torch.no_grad():
            tri = strain_hessian(cloth, x, project)[0].numpy()
            hinge = bending_hessian(cloth, x)[0].numpy()
            vert = np.zeros((cloth.num_vertices, 3, 3))
            if self.inertia is not None:  # M / dt^2 (eq. 5.6)
                vert += (cloth.vertex_mass_kg.numpy() / self.inertia[2] ** 2)[:, None, None] * np.eye(3)
            if self.body is not None:
                vert += self.body.hessian(cloth, x, contacts)[0].numpy()
        return self.assembly.matrix(tri, hinge, vert)


class _LinearSolver:
    """Solves H p = r for the Newton steps of one implicit step, and says when H is not positive definite.

    A sparse LU factorisation (SuperLU in symmetric mode without pivoting, minimum-degree
    ordering on H + H^T: ~0.3 s for the 15k-dof T-shirt, about 1/30 the fill of the default
    ordering) is reused as the preconditioner of conjugate gradients for the next Newton
    iterations, whose Hessians differ little; it is refreshed when CG needs more than ``max_cg``
    iterations or returns a direction of non-positive curvature. Without pivoting the pivots
    are the D of H = L D L^T: all positive iff H is positive definite (Sylvester).
    """

    def __init__(self, rtol: float = 1e-3, max_cg: int = 25):
        self.rtol, self.max_cg = rtol, max_cg
        self._lu = None
        self.factorisations = 0

    def reset(self) -> None:
        self._lu = None

    def solve(self, H: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray | None:
        """p with H p ~ rhs, or None when H is not positive definite."""
        if self._lu is not None:
            M = spla.LinearOperator(H.shape, matvec=self._lu.solve, dtype=np.float64)
            p, info = spla.cg(H, rhs, rtol=self.rtol, maxiter=self.max_cg, M=M)
            if info == 0 and p @ (H @ p) > 0 and p @ rhs > 0:
                return p
        self._lu = spla.splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        self.factorisations += 1
        if not (self._lu.U.diagonal() > 0).all():
            self._lu = None
            return None
        return self._lu.solve(rhs)


def newton_minimize(problem: StepProblem, contacts: Contacts | None, x0: torch.Tensor, tolerance_n: float, max_iterations: int, linear: _LinearSolver | None = None, energy_tolerance_j: float = 0.0) -> tuple[torch.Tensor, dict]:
    """Newton with backtracking (Armijo) line search. Stops ("stop" in the report) when every
    gradient entry is <= tolerance_n (N): "force"; when an iteration lowered the energy by less
    than energy_tolerance_j (J): "energy"; when the line search finds no decrease:
    "line_search"; or after ``max_iterations``: "iterations".

    The exact strain Hessian is used while the system matrix is positive definite (the mass
    term M/dt^2 usually outweighs compression); once it is not (buckling), the PSD projection
    (``strain_hessian(project=True)``) for the rest of the run. With the projected Hessian alone,
    Newton converged only linearly (rate ~0.9 per iteration) in compressed regions (measured).
    Returns the minimiser (1, V, 3) and {"iterations", "evaluations", "stop"}.
    """
    linear = linear or _LinearSolver()
    x = x0.detach().clone()
    evaluations, it, project, stop, last_step = 0, 0, False, "iterations", 0.0

    def fun(y):
        return problem.energy(y, contacts)

    e, g = _value_and_grad(fun, x)
    evaluations += 1
    for it in range(1, max_iterations + 1):
        if g.abs().max() <= tolerance_n:
            it, stop = it - 1, "force"
            break
        rhs = -g.reshape(-1).numpy().astype(np.float64)
        p = linear.solve(problem.hessian(x, contacts, project), rhs)
        if p is None:  # indefinite: switch to the PSD projection (always positive definite with the mass term)
            project = True
            p = linear.solve(problem.hessian(x, contacts, project), rhs)
        slope = float(-rhs @ p) if p is not None else np.nan
        if not np.isfinite(slope) or slope >= 0:  # never expected: steepest descent
            p, slope = rhs, float(-rhs @ rhs)
        p = torch.as_tensor(p.reshape(x.shape), dtype=x.dtype)
        alpha = 1.0
        for _ in range(40):  # Armijo: E(x + a p) <= E(x) + 1e-4 a g.p
            with torch.no_grad():
                e_new = fun(x + alpha * p).sum()
            evaluations += 1
            if e_new <= e + 1e-4 * alpha * slope:
                break
            alpha *= 0.5
        else:
            stop = "line_search"  # no decrease along p: at the precision limit
            break
        x = x + alpha * p
        last_step = float(alpha * p[0].norm(dim=-1).max())
        e_prev = e
        e, g = _value_and_grad(fun, x)
        evaluations += 1
        if log.isEnabledFor(logging.DEBUG):
            f = g[0].norm(dim=-1)
            log.debug("  newton %d: E %.9g J, alpha %.3g, max force %.3g N at vertex %d, step %.3g m%s", it, float(e), alpha, float(f.max()), int(f.argmax()), float(alpha * p[0].norm(dim=-1).max()), " (projected)" if project else "")
        if float(e_prev - e) < energy_tolerance_j:
            stop = "energy" if g.abs().max() > tolerance_n else "force"
            break
    return x, {"iterations": it, "evaluations": evaluations, "stop": stop, "last_step_m": last_step}


def lbfgs_minimize(problem: StepProblem, contacts: Contacts | None, x0: torch.Tensor, tolerance_n: float, max_iterations: int, history_size: int) -> tuple[torch.Tensor, dict]:
    """L-BFGS with strong-Wolfe line search (``minimize_energy``) on ``problem.energy``."""
    x, rep = minimize_energy(lambda y: problem.energy(y, contacts), x0, tolerance_n, max_iterations, history_size)
    stop = "force" if rep["converged"] else ("iterations" if rep["iterations"] >= max_iterations else "line_search")
    return x, {"iterations": rep["iterations"], "evaluations": rep["evaluations"], "stop": stop, "last_step_m": float("nan")}


def solve_step(problem: StepProblem, x_start: torch.Tensor, tolerance_n: float, settings: SolverSettings, residual: str = "energy") -> tuple[torch.Tensor, dict]:
    """Minimise ``problem`` from x_start with the contact planes held fixed per solver run.

    d(x) of eq. 5.12 uses the tangent plane of the closest body vertex; letting that vertex
    change inside a line search makes the energy discontinuous (neighbouring tangent planes
    differ) and stalls the solver. So each run keeps the contacts of its start point (a smooth
    objective), then the contacts are re-selected at the result and the run repeated until they
    no longer change (at most ``settings.contact_rounds`` runs). The report's energies and
    gradients are those with the contacts re-selected at each point (eq. 5.12 with d from the
    closest body vertex). residual: "energy" (the solved objective) or "static" (L_static
    alone: the residual of static equilibrium, for the settle) for the end gradient.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    body = problem.body
    contacts0 = body.contacts(x_start) if body is not None else None
    contacts, x, iterations, evaluations = contacts0, x_start, 0, 0
    linear = _LinearSolver()
    for _ in range(settings.contact_rounds):
        if settings.method == "newton":
            x, rep = newton_minimize(problem, contacts, x, tolerance_n, settings.max_iterations, linear, settings.energy_tolerance_m * problem.cloth.total_mass_kg * GRAVITY_M_S2)
        else:
            x, rep = lbfgs_minimize(problem, contacts, x, tolerance_n, settings.max_iterations, settings.history_size)
        iterations += rep["iterations"]
        evaluations += rep["evaluations"]
        if body is None:
            break
        new = body.contacts(x)
        changed = new.changed(contacts)
        log.debug(" contact round: %d iterations, %d contacts changed", rep["iterations"], changed)
        contacts = new
        if not changed:
            break
    e0, g0 = _value_and_grad(lambda y: problem.energy(y, contacts0), x_start)
    e1, g1 = _value_and_grad(lambda y: problem.energy(y, contacts), x)
    if residual == "static":
        _, g1 = _value_and_grad(lambda y: problem.static(y, contacts), x)
    return x, {
        "iterations": iterations,
        "evaluations": evaluations,
        "energy_start_j": float(e0),
        "energy_end_j": float(e1),
        "grad_norm_start_n": float(g0.norm()),
        "grad_norm_end_n": float(g1.norm()),
        "max_force_n": float(g1.norm(dim=-1).max()),
        "tolerance_n": float(tolerance_n),
        "converged": bool(g1.abs().max() <= tolerance_n),
        "stop": rep["stop"],
        "last_step_m": rep["last_step_m"],
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
    }


def settle(cloth: ClothGeometry, x0: np.ndarray, body_points: np.ndarray, body_faces: np.ndarray, settings: SolverSettings = SolverSettings(), frame: int = 0, steps: int | None = None, candidates: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, list[SolveLog]]:
    """Static equilibrium on a fixed body by a damped dynamic settle (proximal steps, see module doc).

    cloth       : ClothGeometry (dtype of ``settings``)
    x0          : (V, 3) metres, start (e.g. the retarget fit)
    body_points : (M, 3) metres, the fixed body ; body_faces : (Fb, 3)
    steps       : most proximal steps (default ``settings.settle_steps``)
    candidates  : contact candidates (``Collider``), default the closest posed body vertex
    returns     : (V, 3) float32 metres and one SolveLog per step ("settle"); its end gradient
                  is that of the static energy alone (the residual of static equilibrium), and
                  the loop stops once it is below tolerance
    """
    dtype = settings.torch_dtype
    tol = tolerance_newtons(cloth, settings)
    h = settings.settle_dt_s
    x = torch.as_tensor(np.asarray(x0, np.float64)[None], dtype=dtype)
    body = Collider(body_points, body_faces, dtype, candidates, settings.exclusion_radius_m, settings.contact_smoothing_m, settings.candidates)
    assembly = HessianAssembly(cloth) if settings.method == "newton" else None
    logs: list[SolveLog] = []
    for k in range(settings.settle_steps if steps is None else steps):
        problem = StepProblem(cloth, assembly, (x, x, h), body)  # eq. 5.4 with v = 0: a proximal step
        x, rep = solve_step(problem, x, tol, settings, residual="static")
        logs.append(SolveLog(kind="settle", frame=frame, substep=k, **rep))
        log.debug("settle frame %d step %d: %d it, E %.6g -> %.6g J, static |g| %.3g N, max force %.3g N",
                  frame, k, rep["iterations"], rep["energy_start_j"], rep["energy_end_j"], rep["grad_norm_end_n"], rep["max_force_n"])
        if rep["converged"]:
            break
    return x[0].numpy().astype(np.float32), logs


def simulate(
    cloth: ClothGeometry,
    x0: np.ndarray,
    body_frames: np.ndarray | None,
    body_faces: np.ndarray | None,
    fps: float,
    substeps: int = 1,
    settings: SolverSettings = SolverSettings(),
    v0: np.ndarray | None = None,
    driver: np.ndarray | None = None,
    num_frames: int | None = None,
    contacts: RestPoseContacts | None = None,
) -> tuple[np.ndarray, SimulationLog]:
    """Backward-Euler dynamics (eq. 5.4) against a moving collider.

    cloth       : ClothGeometry
    x0          : (V, 3) metres, frame 0 (taken as is)
    body_frames : (T, M, 3) metres, posed collider per frame, or None (no collider: give num_frames)
    body_faces  : (Fb, 3) ; fps : frames per second ; substeps : implicit steps per frame,
                  dt = 1 / (fps substeps); the collider is interpolated linearly between frames
    v0          : (V, 3) m/s initial velocity (default 0)
    driver      : (T, V, 3) metres, optional kinematic positions (the skinned garment) whose
                  per-step displacement moves the warm start; default warm start x + dt v
    contacts    : RestPoseContacts for the frames, or None (closest posed body vertex)
    returns     : (T, V, 3) float32 metres and the SimulationLog
    """
    V = cloth.num_vertices
    if body_frames is not None:
        body_frames = np.asarray(body_frames, np.float64)
        if body_frames.ndim != 3 or body_frames.shape[-1] != 3:
            raise ValueError(f"body_frames: expected shape (T, M, 3), got {body_frames.shape}")
        T = body_frames.shape[0]
    elif num_frames is None:
        raise ValueError("simulate: give body_frames or num_frames")
    else:
        T = num_frames
    if np.asarray(x0).shape != (V, 3):
        raise ValueError(f"x0: expected shape ({V}, 3), got {np.asarray(x0).shape}")
    if driver is not None and np.asarray(driver).shape != (T, V, 3):
        raise ValueError(f"driver: expected shape ({T}, {V}, 3), got {np.asarray(driver).shape}")
    if substeps < 1 or not fps > 0:
        raise ValueError(f"substeps >= 1 and fps > 0 expected, got {substeps}, {fps}")
    dtype = settings.torch_dtype
    dt = 1.0 / (fps * substeps)
    tol = tolerance_newtons(cloth, settings)
    assembly = HessianAssembly(cloth) if settings.method == "newton" else None

    x = torch.as_tensor(np.asarray(x0, np.float64)[None], dtype=dtype)
    v = torch.zeros_like(x) if v0 is None else torch.as_tensor(np.asarray(v0, np.float64)[None], dtype=dtype)
    out = np.empty((T, V, 3), np.float32)
    out[0] = x[0].numpy()
    sim_log = SimulationLog()
    frame_seconds, frame_cpu = np.zeros(T), np.zeros(T)
    for t in range(1, T):
        t0, c0 = time.perf_counter(), time.process_time()
        for s in range(substeps):
            a0, a1 = s / substeps, (s + 1) / substeps
            if driver is not None:  # move with the body: x + (driver(t_end) - driver(t_start))
                step = (a1 - a0) * (np.asarray(driver[t], np.float64) - driver[t - 1])
                guess = x + torch.as_tensor(step[None], dtype=dtype)
            else:
                guess = x + dt * v
            body = None
            if body_frames is not None:
                body = Collider((1 - a1) * body_frames[t - 1] + a1 * body_frames[t], body_faces, dtype, contacts, settings.exclusion_radius_m, settings.contact_smoothing_m, settings.candidates)
            problem = StepProblem(cloth, assembly, (x, x - dt * v, dt), body)  # x_hat = x + dt v (eq. 5.4)
            x_new, rep = solve_step(problem, guess, tol, settings)
            sim_log.solves.append(SolveLog(kind="dynamic", frame=t, substep=s, **rep))
            v = (x_new - x) / dt
            x = x_new
        out[t] = x[0].numpy()
        frame_seconds[t], frame_cpu[t] = time.perf_counter() - t0, time.process_time() - c0
        last = sim_log.solves[-1]
        log.info("frame %d/%d: %.2f s (cpu %.2f s), %d it (last substep), E %.6g -> %.6g J, |g| %.3g N, max force %.3g N, last step %.2g m, stop: %s",
                 t, T - 1, frame_seconds[t], frame_cpu[t], last.iterations, last.energy_start_j, last.energy_end_j,
                 last.grad_norm_end_n, last.max_force_n, last.last_step_m, last.stop)
    sim_log.frame_seconds, sim_log.frame_cpu_seconds = frame_seconds, frame_cpu
    sim_log.frame_energies = frame_energy_terms(cloth, out, body_frames, body_faces, fps, settings)
    return out, sim_log


def frame_energy_terms(cloth: ClothGeometry, frames: np.ndarray, body_frames: np.ndarray | None, body_faces: np.ndarray | None, fps: float, settings: SolverSettings = SolverSettings()) -> dict[str, np.ndarray]:
    """Energy terms (J) of each output frame (T, V, 3): strain, bending, gravity, collision
    against ``body_frames`` (T, M, 3) when given (closest body vertex among
    ``settings.candidates`` KD-tree candidates), inertia over the frames (dt = 1/fps, eq. 5.6;
    0 for frames 0 and 1)."""
    dtype = settings.torch_dtype
    T = len(frames)
    x = torch.as_tensor(np.asarray(frames, np.float64), dtype=dtype)
    terms: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for k, val in energy_terms(cloth, x).items():
            terms[k] = val.numpy().astype(np.float64)
        if body_frames is not None:
            col = np.zeros(T)
            for t in range(T):
                pts = np.asarray(body_frames[t], np.float64)
                nrm = vertex_normals(pts.astype(np.float32), body_faces)
                cand = torch.as_tensor(body_candidates(frames[t][None], pts[None], settings.candidates))
                col[t] = float(collision_energy(cloth, x[t : t + 1], torch.as_tensor(pts[None], dtype=dtype), torch.as_tensor(nrm[None], dtype=dtype), cand)[0])
            terms["collision"] = col
        inertia = np.zeros(T)
        if T > 2:
            inertia[2:] = inertia_energy(cloth, x[2:], x[1:-1], x[:-2], 1.0 / fps).numpy()
        terms["inertia"] = inertia
    return terms


# ------------------------------------------------------------------------------ garments on anny
def quasi_static_drape(asset, body: BodyModel, phenotypes: np.ndarray, settings: SolverSettings = SolverSettings(), cloth: ClothGeometry | None = None) -> tuple[np.ndarray, list[SolveLog]]:
    """Static equilibrium of a garment on a shaped body in the rest pose (no inertia in the result).

    Starts from the ``.mhclo`` retarget fit and runs ``settle`` (damped proximal steps, nothing
    pinned, the body holds the garment through the collision term).
    asset      : inference.garment.GarmentAsset
    phenotypes : (6,) in [0, 1] (PHENOTYPE_LABELS order)
    returns    : (V, 3) float32 metres (the shaped body's rest pose) and the settle log
    """
    phenotypes = np.asarray(phenotypes, np.float32)
    if phenotypes.shape != (6,):
        raise ValueError(f"phenotypes: expected shape (6,), got {phenotypes.shape}")
    cloth = cloth or ClothGeometry.from_asset(asset, settings.torch_dtype)
    shape = body.shape(phenotypes[None])
    x0 = asset.retarget_fit(body.hm08_vertices(shape))[0]
    return settle(cloth, x0, shape.rest_vertices[0], body.faces, settings)


def simulate_sequence(
    asset,
    body: BodyModel,
    phenotypes: np.ndarray,
    rotations: np.ndarray,
    translation: np.ndarray,
    fps: float,
    substeps: int = 2,
    settings: SolverSettings = SolverSettings(),
    drape: np.ndarray | None = None,
    lead_in_frames: int = 15,
) -> tuple[np.ndarray, SimulationLog]:
    """Reference simulation of one garment on one body along a motion.

    Starts from the quasi-static drape on the shaped body in the rest pose (computed unless
    given, (V, 3)), at rest. Skinning that drape straight into the clip's first pose distorts it
    (measured: 40 J of strain for the T-shirt into walk frame 0, arms lowered from the A-pose),
    so the body first moves from the rest pose to the first pose over ``lead_in_frames`` frames
    (``lead_in_motion``) and the garment is simulated along; then frames 0..T-1 of the clip.
    Each step: backward Euler (eq. 5.4), warm start moved by the skinned drape's displacement,
    contacts among rest-pose candidates (``RestPoseContacts``).

    phenotypes  : (6,) ; rotations : (T, 31, 3) axis-angle radians ; translation : (T, 3) metres
    fps         : frames per second ; substeps : implicit steps per frame
    returns     : (T, V, 3) float32 metres and the SimulationLog: solves of the drape ("settle"),
                  the lead-in ("lead_in", frames 1 - lead_in_frames..0) and the clip ("dynamic",
                  frames 1..T-1); per-frame energies and times for the T clip frames
    """
    phenotypes = np.asarray(phenotypes, np.float32)
    rotations = np.asarray(rotations, np.float32)
    translation = np.asarray(translation, np.float32)
    T = rotations.shape[0]
    if T < 1 or rotations.shape != (T, body.num_bones, 3) or translation.shape != (T, 3):
        raise ValueError(f"rotations (T, {body.num_bones}, 3) and translation (T, 3) expected, got {rotations.shape}, {translation.shape}")
    if lead_in_frames < 0:
        raise ValueError(f"lead_in_frames: expected >= 0, got {lead_in_frames}")
    cloth = ClothGeometry.from_asset(asset, settings.torch_dtype)
    drape_log: list[SolveLog] = []
    if drape is None:
        drape, drape_log = quasi_static_drape(asset, body, phenotypes, settings, cloth)
    L = lead_in_frames
    lead_rot, lead_trans = lead_in_motion(rotations, translation, L)
    all_rot, all_trans = np.concatenate([lead_rot, rotations]), np.concatenate([lead_trans, translation])
    shape = body.shape(phenotypes[None])
    _, transforms = body.pose(shape.rest_bone_poses, all_rot[None], all_trans[None])
    body_frames = body.skin(shape.rest_vertices, transforms)[0]  # (L + T, M, 3)
    driver = linear_blend_skinning(np.asarray(drape, np.float32)[None], asset.skin_weights, transforms)[0]  # (L + T, V, 3)
    contacts = RestPoseContacts(drape, shape.rest_vertices[0], asset.skin_weights, body.dense_weights, settings.candidates)
    frames, sim_log = simulate(cloth, driver[0], body_frames, body.faces, fps, substeps, settings, driver=driver, contacts=contacts)
    lead = [replace(x, kind="lead_in", frame=x.frame - L) for x in sim_log.solves if x.frame <= L]
    clip = [replace(x, frame=x.frame - L) for x in sim_log.solves if x.frame > L]
    sim_log.solves = drape_log + lead + clip
    sim_log.frame_energies = {k: v[L:] for k, v in sim_log.frame_energies.items()}  # inertia of frames 0, 1 from the lead-in
    sim_log.frame_seconds, sim_log.frame_cpu_seconds = sim_log.frame_seconds[L:], sim_log.frame_cpu_seconds[L:]
    return frames[L:], sim_log


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> None:
    from inference.garment import GarmentCatalog
    from inference.motion.clips import ClipLibrary, adapt_clip

    p = argparse.ArgumentParser(description="Physics reference simulation of a catalog garment along a motion clip.")
    p.add_argument("--garment", required=True, help="garment id (assets/garments/<id>)")
    p.add_argument("--clip", required=True, help="motion clip id (assets/motions)")
    p.add_argument("--frames", type=int, default=60, help="frames to simulate from --start (default 60)")
    p.add_argument("--start", type=int, default=0, help="first clip frame")
    p.add_argument("--phenotypes", type=float, nargs=6, default=NEUTRAL_PHENOTYPES.tolist(), metavar="P", help="body phenotypes (default neutral)")
    p.add_argument("--substeps", type=int, default=2)
    p.add_argument("--lead-in", type=int, default=15, help="frames from the rest pose to the clip's first pose (simulate_sequence)")
    p.add_argument("--max-iterations", type=int, default=SolverSettings.max_iterations)
    p.add_argument("--force-tolerance", type=float, default=SolverSettings.force_tolerance)
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: fastest for these sizes, and on a shared machine)")
    p.add_argument("--save-body", action="store_true", help="also store the posed body vertices (T, M, 3)")
    p.add_argument("--out", type=Path, required=True, help="output .npz")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    torch.set_num_threads(args.threads)

    settings = SolverSettings(dtype=args.dtype, max_iterations=args.max_iterations, force_tolerance=args.force_tolerance)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(args.garment)
    phen = np.asarray(args.phenotypes, np.float32)
    shape = body.shape(phen[None])
    clip = ClipLibrary().load(args.clip)
    rotations, translation = adapt_clip(clip, body, shape)
    sl = slice(args.start, args.start + args.frames)
    rotations, translation = rotations[0, sl], translation[0, sl]

    t0 = time.perf_counter()
    drape, drape_log = quasi_static_drape(asset, body, phen, settings)
    t_drape = time.perf_counter() - t0
    log.info("quasi-static drape: %d steps, %.1f s, static |g| %.3g N (converged %s)", len(drape_log), t_drape,
             drape_log[-1].grad_norm_end_n if drape_log else float("nan"), drape_log[-1].converged if drape_log else True)
    t1 = time.perf_counter()
    frames, sim_log = simulate_sequence(asset, body, phen, rotations, translation, clip.fps, args.substeps, settings, drape=drape, lead_in_frames=args.lead_in)
    t_sim = time.perf_counter() - t1
    sim_log.solves = drape_log + sim_log.solves
    dyn = sim_log.summary("dynamic")
    meta = {
        "garment": args.garment, "clip": args.clip, "start": args.start, "frames": int(len(frames)),
        "fps": clip.fps, "substeps": args.substeps, "settings": asdict(settings),
        "material": asdict(ClothGeometry.from_asset(asset).material),
        "seconds_drape": t_drape, "seconds_simulation": t_sim,
        "lead_in": args.lead_in, "seconds_per_frame": t_sim / (len(frames) - 1 + args.lead_in),
        "cpu_seconds_per_clip_frame": float(np.mean(sim_log.frame_cpu_seconds[1:])) if len(frames) > 1 else 0.0,
        "dynamic_solves": dyn, "lead_in_solves": sim_log.summary("lead_in"), "settle_solves": sim_log.summary("settle"),
        "machine": f"{platform.machine()} {platform.processor()}, {os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}",
        "load_average_1min_end": os.getloadavg()[0],
        "git_commit": _git_commit(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    body_frames = None
    if args.save_body:
        _, transforms = body.pose(shape.rest_bone_poses, rotations[None], translation[None])
        body_frames = body.skin(shape.rest_vertices, transforms)[0]
    np.savez_compressed(
        args.out,
        vertices=frames, faces=asset.faces.astype(np.int32), drape=drape,
        phenotypes=phen, rotations=rotations, translation=translation, fps=np.float32(clip.fps),
        metadata=np.str_(json.dumps(meta)),
        **({"body_vertices": body_frames} if body_frames is not None else {}),
        **sim_log.arrays(),
    )
    log.info("wrote %s: %d frames, %.2f s/frame; dynamic solves %s", args.out, len(frames), meta["seconds_per_frame"], json.dumps(dyn))


if __name__ == "__main__":
    main()
