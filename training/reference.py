"""Physics reference: newton's VBD cloth solver (a well-kept simulator) along a motion.

The project's judge (DESIGN.md §5, §7): every garment method is compared with this simulation
of the same garment, body and motion. newton (NVIDIA, on warp) integrates the cloth with Vertex
Block Descent (Chen et al. 2024); it runs on the CPU (single-threaded warp kernels) or a GPU.

Material mapping, SNUG (DESIGN.md §3, thesis ch. 5.3.1) -> newton ``add_cloth_mesh``:

    SNUG (volumetric, eq. 5.8-5.10)         newton VBD (per rest area)
    mu      = 2.36e4 Pa                 ->  tri_ke  = mu * h        = 11.09 N/m
    lambda  = 4.44e4 Pa                 ->  tri_ka  = lambda * h    = 20.87 N/m
    rho     = 426 kg/m^3, h = 0.47 mm   ->  density = rho * h       = 0.200 kg/m^2 (per area)
    k_bend  = 3.96e-5 J per rad^2,          E_e = k_bend l^2 / (4 (a1 + a2)) (dtheta)^2 / 2
                                        ->  E_e = ke_e l (dtheta)^2 / 2, so per edge
                                            ke_e = k_bend l / (4 (a1 + a2))   (N/rad^2... J/m)
                                            (``edge_bending_properties[:, 0]``, set per edge)

newton's membrane is the stable Neo-Hookean shell (Smith et al. 2018) with the same Lame
parameters, equal to SNUG's StVK to first order in the strain; it differs at large strain, where
StVK softens under compression (the reason SNUG's garments can crumple without energy).

Body: the posed, shaped anny body (the service's motion import: retarget, arms lifted as
``inference.motion.self_contact`` does by default) as a static triangle-mesh collider whose
points and velocities are updated every substep (linear interpolation between frames,
velocity = frame difference / frame time) and whose BVH is refitted; newton has no deforming-mesh
collider of its own. Its local bounds are widened to the whole motion once, so that the broad
phase never culls a contact on a moving body. Contact: newton's soft body-particle contact with a
particle radius equal to the garment's collision margin (``material.collision_margin_m``),
friction ``friction`` (Coulomb, 0.3 cloth on skin; 0 matches the SNUG losses, which have none).
No cloth self-contact (SNUG's losses have none either).

Waistbands: a bottom (``category`` 'bottom': trousers) is held up in life by an elastic waistband
tighter than the hips, which a membrane at its rest size cannot model; left free, the simulated
trousers slid down to the ankles within a second (seen on the contact sheet of 02_02). Their
waist opening (the border loop highest in the rest shape, ``waistband_vertices``) is therefore
kinematic: it follows the skinned retarget fit, as simulators pin a waistband (HOOD, ContourCraft).

Necklines: the open-front jacket (``category`` 'outer') is the jacket of a suit whose collar was
left out of the asset; its raw neckline sits loose around the neck, and the simulated jacket slid
back and down off the shoulders within a second of the validation walk (02_02, neutral: 14 % of
its vertices more than 5 cm farther from the body than the skinned fit, seen on its contact
sheet). The collar that holds a jacket's neckline on the shoulders is modelled the same way as a
waistband: the neckline (``collar_vertices``) follows the skinned retarget fit; the fronts, hem
and sleeves stay free.

Sequence: the ``.mhclo`` retarget of the garment on the shaped body in the rest pose, a lead-in
from the rest pose to the clip's first pose (``lead_in_frames``, smoothstep per joint), a settle
period holding the first pose (``settle_frames``: the garment comes to rest under gravity), then
the clip's frames. Rest geometry: the garment asset's ``rest_vertices`` (as ``training.physics``).

CLI: ``python -m training.reference --garment tshirt --clip 02_02 --frames 30
--out build/reference/tshirt_02_02.npz``.

Units: metres, seconds, kg, N. Arrays float32 numpy at the interface.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, linear_blend_skinning
from inference.garment import GarmentAsset
from training.protocol import lead_in_motion

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class ReferenceSettings:
    """Simulator settings (every one is written into the output's metadata).

    substeps        : VBD steps per frame (dt = 1 / (fps substeps))
    iterations      : VBD iterations per step
    friction        : Coulomb friction between cloth and body (0.3 cloth on skin; 0 = SNUG)
    contact_ke      : body-particle contact stiffness, N/m (newton's penalty; AVBD ramps it)
    contact_kd      : contact damping, s (newton's units: force = kd ke dv)
    tri_kd, edge_kd : membrane and bending damping (newton's Rayleigh-style coefficients, s)
    lead_in_frames  : frames from the rest pose to the clip's first pose
    settle_frames   : frames holding the first pose before the clip starts
    device          : warp device ('cpu' or 'cuda:0'; None: warp's default)
    """

    substeps: int = 20
    iterations: int = 10
    friction: float = 0.3
    contact_ke: float = 1.0e4
    contact_kd: float = 1.0e-3
    tri_kd: float = 1.0e-4
    edge_kd: float = 1.0e-6
    lead_in_frames: int = 10
    settle_frames: int = 10
    device: str | None = None

    def __post_init__(self):
        if self.substeps < 1 or self.iterations < 1:
            raise ValueError(f"substeps and iterations must be >= 1, got {self.substeps}, {self.iterations}")
        if self.lead_in_frames < 0 or self.settle_frames < 0:
            raise ValueError("lead_in_frames and settle_frames must be >= 0")
        if not (0.0 <= self.friction <= 2.0):
            raise ValueError(f"friction must be in [0, 2], got {self.friction}")


def bending_stiffness_per_edge(rest: np.ndarray, edge_indices: np.ndarray, k_bend: float) -> np.ndarray:
    """newton's per-edge bending ke (E_e = ke l dtheta^2 / 2) equal to SNUG's eq. 5.10
    (E_e = k_bend l^2 / (4 (a1 + a2)) dtheta^2 / 2): ke = k_bend l / (4 (a1 + a2)).

    rest         : (V, 3) rest positions, metres
    edge_indices : (E, 4) newton's (opposite 0, opposite 1, edge start, edge end); -1 on a border
    returns      : (E,) float32 (0 on border edges, which have no hinge)
    """
    e = np.asarray(edge_indices)
    valid = (e[:, 0] >= 0) & (e[:, 1] >= 0)
    x = rest[np.where(valid[:, None], e, 0)]
    edge = x[:, 3] - x[:, 2]
    l = np.linalg.norm(edge, axis=1)
    a1 = 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]), axis=1)
    a2 = 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 1], x[:, 3] - x[:, 1]), axis=1)
    ke = k_bend * l / np.maximum(4.0 * (a1 + a2), 1e-12)
    return np.where(valid, ke, 0.0).astype(np.float32)


def waistband_vertices(asset: GarmentAsset) -> np.ndarray:
    """Vertices of the waist opening of a bottom garment: the border loop (edges of one face)
    with the highest mean z in the rest shape. Other categories: none. returns (P,) int64."""
    if asset.category != "bottom":
        return np.zeros(0, np.int64)
    return _highest_border_loop(asset)


def _highest_border_loop(asset: GarmentAsset) -> np.ndarray:
    """The border loop (edges of one face, connected) with the highest mean rest z. (P,) int64."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(asset.faces, np.int64)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    border = uniq[count == 1]
    V = asset.num_vertices
    g = sp.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(V, V))
    _, label = connected_components(g, directed=False)
    ids = np.unique(border)
    loops = {lab: ids[label[ids] == lab] for lab in np.unique(label[ids])}
    z = np.asarray(asset.rest_vertices)[:, 2]
    return max(loops.values(), key=lambda v: z[v].mean()).astype(np.int64)


COLLAR_DEPTH_M = 0.05


def collar_vertices(asset: GarmentAsset) -> np.ndarray:
    """Vertices of the neckline of an outer garment (``category`` 'outer': the open jacket): the
    vertices of the highest border loop within ``COLLAR_DEPTH_M`` of the garment's top in the
    rest shape (the back neck and the shoulder-neck points; an open front's loop runs on down the
    front edges and the hem, which stay free). Other categories: none. returns (P,) int64."""
    if asset.category != "outer":
        return np.zeros(0, np.int64)
    loop = _highest_border_loop(asset)
    z = np.asarray(asset.rest_vertices)[:, 2]
    return loop[z[loop] >= z.max() - COLLAR_DEPTH_M]


def kinematic_vertices(asset: GarmentAsset) -> np.ndarray:
    """The vertices the reference moves with the skinned fit instead of simulating (module
    docstring): a bottom's waistband, an outer garment's neckline. returns (P,) int64."""
    return np.union1d(waistband_vertices(asset), collar_vertices(asset)).astype(np.int64)


@dataclass
class ReferenceResult:
    """vertices : (T, V, 3) float32 metres, the clip's frames; body_vertices : (T, M, 3);
    seconds_per_frame : wall time per simulated frame (lead-in and settle included);
    max_speed_m_s : (T,) largest vertex speed per clip frame (a blow-up shows here)."""

    vertices: np.ndarray
    body_vertices: np.ndarray
    seconds_per_frame: float
    max_speed_m_s: np.ndarray


class ClothOnBody:
    """One garment on one moving body in newton (``simulate`` runs it)."""

    def __init__(self, asset: GarmentAsset, initial: np.ndarray, body_frame0: np.ndarray, body_faces: np.ndarray, settings: ReferenceSettings,
                 pinned: np.ndarray | None = None):
        import newton
        import warp as wp

        self.wp, self.settings = wp, settings
        if settings.device is not None:
            wp.set_device(settings.device)
        m = asset.material
        h = float(m["thickness_m"])
        builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -GRAVITY_M_S2))
        builder.add_cloth_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=[wp.vec3(*p) for p in np.asarray(asset.rest_vertices, np.float64)],
            indices=np.asarray(asset.faces, np.int32).reshape(-1).tolist(),
            density=float(m["density_kg_m3"]) * h,
            tri_ke=float(m["lame_mu_pa"]) * h, tri_ka=float(m["lame_lambda_pa"]) * h, tri_kd=settings.tri_kd,
            edge_ke=float(m["k_bend"]), edge_kd=settings.edge_kd,
            particle_radius=float(m["collision_margin_m"]),
        )
        self.body_mesh = newton.Mesh(np.asarray(body_frame0, np.float32), np.asarray(body_faces, np.int32).reshape(-1), compute_inertia=False)
        cfg = newton.ModelBuilder.ShapeConfig(ke=settings.contact_ke, kd=settings.contact_kd, mu=settings.friction)
        builder.add_shape_mesh(body=-1, mesh=self.body_mesh, cfg=cfg)
        builder.color(include_bending=True)
        model = builder.finalize()
        model.soft_contact_ke = settings.contact_ke
        model.soft_contact_kd = settings.contact_kd
        model.soft_contact_mu = settings.friction
        # SNUG bending per edge (module docstring), from the rest geometry
        props = model.edge_bending_properties.numpy()
        props[:, 0] = bending_stiffness_per_edge(np.asarray(asset.rest_vertices, np.float64), model.edge_indices.numpy(), float(m["k_bend"]))
        model.edge_bending_properties.assign(props)
        # kinematic vertices (waistband): zero inverse mass, positions set every substep
        self.pinned = np.zeros(0, np.int64) if pinned is None else np.asarray(pinned, np.int64)
        if len(self.pinned):
            for name in ("particle_inv_mass", "particle_mass"):  # the solver reads both
                values = getattr(model, name).numpy()
                values[self.pinned] = 0.0
                getattr(model, name).assign(values)
        self.model = model
        self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=2.0 * float(m["collision_margin_m"]))
        self.contacts = self.pipeline.contacts()
        self.solver = newton.solvers.SolverVBD(model, iterations=settings.iterations)
        self.state0, self.state1 = model.state(), model.state()
        self.control = model.control()
        self.state0.particle_q.assign(np.asarray(initial, np.float32))
        self.state0.particle_qd.zero_()

    def widen_collider_bounds(self, lower: np.ndarray, upper: np.ndarray) -> None:
        """Local collision bounds of the body shape: the whole motion's box (metres)."""
        self.model.shape_collision_aabb_lower.assign(np.asarray([lower], np.float32))
        self.model.shape_collision_aabb_upper.assign(np.asarray([upper], np.float32))
        radius = float(np.linalg.norm(np.asarray(upper) - np.asarray(lower)))
        self.model.shape_collision_radius.assign(np.asarray([radius], np.float32))

    def set_body(self, points: np.ndarray, velocities: np.ndarray) -> None:
        mesh = self.body_mesh.mesh
        mesh.points.assign(np.asarray(points, np.float32))
        mesh.velocities.assign(np.asarray(velocities, np.float32))
        mesh.refit()

    def set_pinned(self, points: np.ndarray, velocities: np.ndarray) -> None:
        q, qd = self.state0.particle_q.numpy(), self.state0.particle_qd.numpy()
        q[self.pinned], qd[self.pinned] = points, velocities
        self.state0.particle_q.assign(q)
        self.state0.particle_qd.assign(qd)

    def step_frame(self, body_a: np.ndarray, body_b: np.ndarray, frame_dt: float, pin_a: np.ndarray | None = None, pin_b: np.ndarray | None = None) -> None:
        """One frame: ``substeps`` VBD steps with the body (and the pinned vertices, (P, 3))
        moving linearly from a to b."""
        n = self.settings.substeps
        dt = frame_dt / n
        velocity = (body_b - body_a) / frame_dt
        for k in range(n):
            s = (k + 1) / n
            if len(self.pinned):
                self.set_pinned(pin_a + s * (pin_b - pin_a), (pin_b - pin_a) / frame_dt)
            self.set_body(body_a + s * (body_b - body_a), velocity)
            self.pipeline.collide(self.state0, self.contacts)
            self.state0.clear_forces()
            self.solver.step(self.state0, self.state1, self.control, self.contacts, dt)
            self.state0, self.state1 = self.state1, self.state0

    @property
    def positions(self) -> np.ndarray:
        return self.state0.particle_q.numpy().astype(np.float32)

    @property
    def velocities(self) -> np.ndarray:
        return self.state0.particle_qd.numpy().astype(np.float32)


def simulate(asset: GarmentAsset, body: BodyModel, phenotypes: np.ndarray, rotations: np.ndarray, translation: np.ndarray,
             fps: float, settings: ReferenceSettings = ReferenceSettings()) -> ReferenceResult:
    """Reference simulation of ``asset`` on the body of ``phenotypes`` (6,) along a motion
    already retargeted to that body: rotations (T, J, 3) radians, translation (T, 3) metres.

    returns the clip's T frames (module docstring: lead-in and settle come first, not returned)
    """
    rotations = np.asarray(rotations, np.float32)
    translation = np.asarray(translation, np.float32)
    T = rotations.shape[0]
    if T < 1 or rotations.shape != (T, body.num_bones, 3) or translation.shape != (T, 3):
        raise ValueError(f"rotations (T, {body.num_bones}, 3) and translation (T, 3) expected, got {rotations.shape}, {translation.shape}")
    shape = body.shape(np.asarray(phenotypes, np.float32)[None])
    L, S = settings.lead_in_frames, settings.settle_frames
    lead_rot, lead_trans = lead_in_motion(rotations, translation, L)
    all_rot = np.concatenate([lead_rot, np.repeat(rotations[:1], S, 0), rotations])
    all_trans = np.concatenate([lead_trans, np.repeat(translation[:1], S, 0), translation])
    _, transforms = body.pose(shape.rest_bone_poses, all_rot[None], all_trans[None])
    body_frames = body.skin(shape.rest_vertices, transforms)[0]  # (L + S + T, M, 3)
    rest_fit = asset.retarget_fit(body.hm08_vertices(shape))  # (1, V, 3), rest pose of the shaped body
    # frame 0 of the sequence: the rest pose shifted to t_0 (the lead-in's start) or, without a
    # lead-in or settle, the clip's first pose, the fit skinned into it
    initial = linear_blend_skinning(rest_fit, asset.skin_weights, transforms[:, :1])[0, 0]
    pinned = kinematic_vertices(asset)
    # the pinned vertices follow the skinned fit: (L + S + T, P, 3)
    pin_frames = linear_blend_skinning(rest_fit[:, pinned], asset.skin_weights[pinned], transforms)[0] if len(pinned) else None
    sim = ClothOnBody(asset, initial, body_frames[0], body.faces, settings, pinned)
    pad_m = 0.5
    sim.widen_collider_bounds(body_frames.min(axis=(0, 1)) - pad_m, body_frames.max(axis=(0, 1)) + pad_m)
    frame_dt = 1.0 / float(fps)
    first_clip = L + S
    out = np.empty((T,) + initial.shape, np.float32)
    speed = np.zeros(T, np.float32)
    if first_clip == 0:
        out[0] = initial
    t0 = time.perf_counter()
    for f in range(1, len(body_frames)):
        if pin_frames is None:
            sim.step_frame(body_frames[f - 1], body_frames[f], frame_dt)
        else:
            sim.step_frame(body_frames[f - 1], body_frames[f], frame_dt, pin_frames[f - 1], pin_frames[f])
        if f >= first_clip:
            q = sim.positions
            if not np.isfinite(q).all():
                raise FloatingPointError(f"simulation diverged at frame {f - first_clip}")
            out[f - first_clip] = q
            speed[f - first_clip] = float(np.linalg.norm(sim.velocities, axis=1).max())
        if f % 10 == 0:
            log.info("frame %d/%d (%.2f s/frame)", f, len(body_frames) - 1, (time.perf_counter() - t0) / f)
    seconds = (time.perf_counter() - t0) / max(len(body_frames) - 1, 1)
    return ReferenceResult(out, body_frames[first_clip:].astype(np.float32), seconds, speed)


REFERENCE_DIR = Path(__file__).resolve().parents[1] / "build" / "reference" / "newton"


def reference_path(garment: str, case_key: str, settings: ReferenceSettings, directory: Path = REFERENCE_DIR) -> Path:
    """Cache file of one simulation (outside git: ``build/``)."""
    return directory / f"{garment}_{case_key}_mu{settings.friction:g}_s{settings.substeps}_i{settings.iterations}.npz"


def simulate_case(garment: str, case, settings: ReferenceSettings = ReferenceSettings(), directory: Path = REFERENCE_DIR,
                  body: BodyModel | None = None, catalog=None) -> Path:
    """Simulate one garment on one protocol case (``training.protocol.Case``) unless cached;
    returns the .npz path (vertices (T, V, 3), body_vertices (T, M, 3), metadata JSON)."""
    from inference.garment import GarmentCatalog
    from training.protocol import BODIES, case_motion

    path = reference_path(garment, case.key, settings, directory)
    if path.exists():
        return path
    body = body or BodyModel.load()
    asset = (catalog or GarmentCatalog.load()).get(garment)
    shape, motion, start = case_motion(body, case)
    # the simulation starts at the window: lead-in from the rest pose to frame ``start``
    result = simulate(asset, body, BODIES[case.body], motion.rotations[start:], motion.translation[start:], motion.fps, settings)
    meta = {
        "garment": garment, "case": case.name, "clip": case.clip, "body": case.body, "start": case.start, "frames": case.frames,
        "fps": motion.fps, "settings": asdict(settings), "material": asset.material,
        "seconds_per_frame": result.seconds_per_frame, "kinematic_vertices": int(len(kinematic_vertices(asset))),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, warp device {settings.device or 'default'}",
        "newton": _version("newton"), "warp": _version("warp-lang"),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, vertices=result.vertices, body_vertices=result.body_vertices, max_speed_m_s=result.max_speed_m_s,
                        faces=np.asarray(asset.faces, np.int32), metadata=np.str_(json.dumps(meta)))
    tmp.replace(path)
    log.info("wrote %s (%.2f s/frame)", path, result.seconds_per_frame)
    return path


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "absent"


def main(argv: list[str] | None = None) -> None:
    from training.protocol import SMOKE, SPLITS, Case

    p = argparse.ArgumentParser(description="newton VBD reference simulation of catalog garments on protocol cases.")
    p.add_argument("--garment", action="append", required=True, help="garment id (repeatable)")
    p.add_argument("--split", action="append", choices=sorted(SPLITS) + ["smoke"], help="every case of a protocol split (repeatable)")
    p.add_argument("--clip", help="one case: clip id (bundled or CMU AMC under training/sources)")
    p.add_argument("--body", default="neutral", help="one case: body name of training.protocol.BODIES")
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--friction", type=float, default=ReferenceSettings.friction)
    p.add_argument("--substeps", type=int, default=ReferenceSettings.substeps)
    p.add_argument("--iterations", type=int, default=ReferenceSettings.iterations)
    p.add_argument("--lead-in", type=int, default=ReferenceSettings.lead_in_frames)
    p.add_argument("--settle", type=int, default=ReferenceSettings.settle_frames)
    p.add_argument("--device", default=None, help="warp device: cpu, cuda:0 (default: warp's)")
    p.add_argument("--out-dir", type=Path, default=REFERENCE_DIR)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    settings = ReferenceSettings(substeps=args.substeps, iterations=args.iterations, friction=args.friction,
                                 lead_in_frames=args.lead_in, settle_frames=args.settle, device=args.device)
    if args.split:
        cases = [c for split in args.split for c in ([SMOKE] if split == "smoke" else SPLITS[split])]
    elif args.clip:
        cases = [Case(args.clip, args.body, args.start, args.frames)]
    else:
        p.error("give --split or --clip")
    body = BodyModel.load()
    for g in args.garment:
        for case in cases:
            t0 = time.perf_counter()
            path = simulate_case(g, case, settings, args.out_dir, body)
            log.info("%s on %s: %s (%.0f s)", g, case.name, path, time.perf_counter() - t0)


if __name__ == "__main__":
    main()
