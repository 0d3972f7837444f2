"""Physics reference: implicit backward-Euler cloth simulation by energy minimisation.

Each time step solves eq. 5.4 (the minimisation form of backward Euler, eq. 5.3):

    x^{t+1} = argmin_x  L_inertia(x; x^t, v^t, dt) + L_static(x; posed body at t+1)

with exactly the energies the learned models are trained on (``training.physics``: eq. 5.6-5.12),
then v^{t+1} = (x^{t+1} - x^t) / dt. Every solve is logged, so the reference can be judged by
how well it converged, not trusted blindly.

Modules:

- ``settings``: ``SolverSettings`` (every solver hyper-parameter), the convergence logs
  ``SolveLog`` and ``SimulationLog``, ``tolerance_newtons``.
- ``contacts``: which body tangent planes the garment collides with (``RestPoseContacts``,
  ``Contacts``) and the posed body of one solve (``Collider``).
- ``problem``: the objective of one implicit step (``StepProblem``) and the sparse assembly of
  its Hessian (``HessianAssembly``).
- ``optimise``: the minimisers: projected Newton with sparse direct solves (``newton_minimize``,
  the default) and L-BFGS (``minimize_energy``, ``lbfgs_minimize``).
- ``integrator``: one step with contact rounds (``solve_step``), the damped static settle
  (``settle``), dynamics against a moving body (``simulate``), per-frame energies
  (``frame_energy_terms``).
- ``drivers``: garments on the anny body: ``quasi_static_drape`` and ``simulate_sequence``.
- ``cli``: ``python -m training.simulate --garment tshirt --clip walk --frames 60
  --out build/reference/tshirt_walk.npz`` writes the sequence and the convergence log.

Units: metres, seconds, kg, newtons (gradients), joules (energies). Arrays float32 numpy at the
interface, float64 torch inside by default (``SolverSettings.dtype``).
"""
from training.simulate.cli import main
from training.simulate.contacts import Collider, Contacts, RestPoseContacts
from training.simulate.drivers import quasi_static_drape, simulate_sequence
from training.simulate.integrator import frame_energy_terms, settle, simulate, solve_step
from training.simulate.optimise import lbfgs_minimize, minimize_energy, newton_minimize
from training.simulate.problem import HessianAssembly, StepProblem
from training.simulate.settings import SimulationLog, SolveLog, SolverSettings, tolerance_newtons

__all__ = [
    "Collider",
    "Contacts",
    "HessianAssembly",
    "RestPoseContacts",
    "SimulationLog",
    "SolveLog",
    "SolverSettings",
    "StepProblem",
    "frame_energy_terms",
    "lbfgs_minimize",
    "main",
    "minimize_energy",
    "newton_minimize",
    "quasi_static_drape",
    "settle",
    "simulate",
    "simulate_sequence",
    "solve_step",
    "tolerance_newtons",
]
