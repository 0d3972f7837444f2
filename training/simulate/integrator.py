"""Time integration: implicit steps, the damped static settle, and dynamics against a moving body.

- ``solve_step``: one minimisation of a ``StepProblem`` with the contact planes held fixed per
  solver run and re-selected between runs (``SolverSettings.contact_rounds``).
- ``settle``: static equilibrium against a fixed body. A garment held only by frictionless
  contact is not a well-posed static problem from an arbitrary start (it may slide, and the pure
  static energy has near-zero-stiffness modes, a singular Hessian), so it runs a damped dynamic
  settle: implicit steps with the velocity reset to zero after each step, i.e. proximal-point
  iterations x_{k+1} = argmin E_static(x) + 1/(2 h^2) |x - x_k|^2_M, which decrease E_static
  and stop when the static residual |dE_static/dx| is below the tolerance (then the proximal
  term's force M (x_{k+1} - x_k)/h^2 is too). Nothing is pinned: the garment rests on the body
  through the collision term (a T-shirt on the shoulders, trousers on the hips).
- ``simulate``: dynamics against a moving collider given per frame (T, M, 3): each step solves
  eq. 5.4, then v^{t+1} = (x^{t+1} - x^t) / dt; the collider is interpolated linearly for
  substeps, with vertex normals rebuilt per substep; warm start = previous positions moved by
  the garment's skinning displacement (when given) or by the previous velocity.
- ``frame_energy_terms``: the energy terms of each output frame, for the log.

Units: metres, seconds, kg, newtons (gradients), joules (energies). Arrays float32 numpy at the
interface, float64 torch inside by default (``SolverSettings.dtype``).
"""
from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np
import torch

from inference.mesh import vertex_normals
from training.candidates import body_candidates
from training.physics import GRAVITY_M_S2, ClothGeometry, collision_energy, energy_terms, inertia_energy
from training.simulate.contacts import Collider, RestPoseContacts
from training.simulate.optimise import _LinearSolver, _value_and_grad, convergence_report, lbfgs_minimize, newton_minimize
from training.simulate.problem import HessianAssembly, StepProblem
from training.simulate.settings import SimulationLog, SolveLog, SolverSettings, tolerance_newtons

log = logging.getLogger(__name__)


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
        **convergence_report(e0, g0, e1, g1, tolerance_n),
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
