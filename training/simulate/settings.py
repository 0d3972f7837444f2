"""Solver settings and convergence logs of the physics reference.

``SolverSettings`` holds every hyper-parameter of the solver (one place, saved with the outputs);
``SolveLog`` records one energy minimisation (iterations, energy before and after, gradient
norm, largest per-vertex residual force, wall and CPU time) and ``SimulationLog`` a whole run,
so the reference can be judged by how well it converged, not trusted blindly.
``tolerance_newtons`` turns the relative force tolerance into newtons.

Units: metres, seconds, kg, newtons (gradients, forces), joules (energies).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from training.physics import GRAVITY_M_S2, ClothGeometry


@dataclass(frozen=True)
class SolverSettings:
    """Solver hyper-parameters of the physics reference (one place, saved with the outputs).

    method           : "newton" (default: projected Newton, sparse direct solves, backtracking
                       line search) or "lbfgs" (torch.optim.LBFGS, strong-Wolfe line search).
                       Cloth is stiff in-plane: k dt^2 / m = E dt^2 / (rho A) ~ 1e3 for the
                       catalog meshes at 60 Hz, and L-BFGS needs hundreds of iterations where
                       Newton needs a handful (measured, notes of ``training.simulate.optimise``).
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


def tolerance_newtons(cloth: ClothGeometry, settings: SolverSettings) -> float:
    """Per-coordinate gradient tolerance: force_tolerance x mean vertex weight (N)."""
    return settings.force_tolerance * cloth.total_mass_kg / cloth.num_vertices * GRAVITY_M_S2
