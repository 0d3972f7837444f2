"""Garments on the anny body: the quasi-static drape and the simulation along a motion.

- ``quasi_static_drape``: ``settle`` of the ``.mhclo`` retarget fit on the shaped body in the
  rest pose.
- ``simulate_sequence``: on the anny body along a motion: a lead-in from the rest pose (where
  the drape is) to the clip's first pose, then the clip's frames (``simulate``, contacts among
  rest-pose candidates).

Units: metres, seconds; axis-angle radians for the motion's rotations.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from inference.body import BodyModel, linear_blend_skinning
from training.physics import ClothGeometry
from training.protocol import lead_in_motion
from training.simulate.contacts import RestPoseContacts
from training.simulate.integrator import settle, simulate
from training.simulate.settings import SimulationLog, SolveLog, SolverSettings


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
