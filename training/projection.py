"""Projection of posed garments into the canonical space (thesis ch. 6.3.3, eq. 6.9-6.12), torch.

The canonical garment model (eq. 6.7-6.8, ``inference.diffused``) maps a garment X in the
canonical space (unposed, deshaped: on the neutral body in its rest pose) to the posed space:

    T_G(X, beta)        = X + B~s(X, beta)                                       (eq. 6.8)
    M_G(X, beta, theta) = sum_j W~_j(X) T_j(beta, theta) T_G(X, beta)            (eq. 6.7)

Given a posed garment frame x (a physics simulation) with known beta and theta, its canonical
form is

    X* = argmin_X  E_rec + w_strain E_strain + w_collision E_collision           (eq. 6.9)
    E_rec       = mean_v |x_v - M_G(X, beta, theta)_v|^2          (m^2)          (eq. 6.10)
    E_strain    = sum_f a_f |G_f|_F^2 / sum_f a_f,  G = (F^T F - I) / 2           (eq. 6.11)
                  F the deformation gradient of T_G(X, beta) against the garment's rest triangles,
                  a_f their rest areas (unitless)
    E_collision = mean_v max(eps - SDF(X_v), 0)                   (m)            (eq. 6.12)
    E_posed     = mean_v max(eps_p - (M_G(X)_v - b_v) . n_v, 0)   (m, optional)

with SDF the constant canonical body's signed distance (the diffused body's grid). Every term is
differentiable in X through the trilinear fields (W~, B~s and SDF all depend on X). A sequence
is solved frame by frame with L-BFGS, each frame started from the previous frame's X (the thesis'
warm start: faster, and stable in time); the first frame starts from the inverse skinning of the
target with the fields at the garment template.

E_posed (``ProjectionSettings.w_posed`` > 0; not in the thesis) keeps the *posed* garment out of
the simulation's own posed body: b_v and n_v are the body vertex nearest to the target's vertex v
and its unit normal, fixed per frame. Without it, E_rec's millimetres of residual and the
canonical E_collision leave more of the posed garment inside the body than the simulation had
(the trousers' heavy training data: 0.095 % in newton, 0.52 % posed from X*), and a model
trained on X* learns those points.

Units: metres. Arrays: torch float64 inside, numpy float32 at the interface.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from inference.diffused import CORNERS, DEFAULT_PATH, BandGrid, DiffusedBody
from training.physics import ClothGeometry, deformation_gradients


class TorchBandGrid:
    """``inference.diffused.BandGrid`` in torch: the same two-level trilinear interpolation
    (the fine band's cell, a corner off the band read from the coarse grid), clamped to the
    box, differentiable in the points (the tables are constants).

    Tables of few channels (``DENSE_BYTES``) are expanded once to the whole fine grid (a node off
    the band holds the coarse grid's value there, which is what its corner reads) and read by
    ``torch.nn.functional.grid_sample`` (several times faster, backward included); wider ones
    gather the band's rows per call."""

    DENSE_BYTES = 64 << 20

    def __init__(self, grid: BandGrid, fine: np.ndarray, coarse: np.ndarray, dtype: torch.dtype = torch.float64):
        fine, coarse = np.asarray(fine), np.asarray(coarse)
        self.origin = torch.as_tensor(grid.fine.origin, dtype=dtype)
        self.levels = {name: (g.spacing, torch.as_tensor(g.dims), torch.as_tensor(g.strides)) for name, g in (("fine", grid.fine), ("coarse", grid.coarse))}
        self.corners = torch.as_tensor(CORNERS)
        n_dense = int(np.prod(grid.fine.dims))
        self.volume = None
        if n_dense * fine.shape[1] * torch.finfo(dtype).bits // 8 <= self.DENSE_BYTES:
            table = np.empty((n_dense, fine.shape[1]), np.float64)
            on = grid.row >= 0
            table[on] = fine[grid.row[on]]
            off = np.flatnonzero(~on)
            for a in range(0, len(off), 1 << 18):
                ids = off[a:a + (1 << 18)]
                nodes = grid.fine.origin + grid.fine.spacing * np.stack(np.unravel_index(ids, tuple(grid.fine.dims)), -1)
                table[ids] = grid.coarse.interpolate(nodes.astype(np.float32), coarse)
            self.extent = torch.as_tensor((grid.fine.dims - 1).astype(np.float64) * grid.fine.spacing, dtype=dtype)
            # (1, C, nx, ny, nz): grid_sample's (N, C, D, H, W), so a point's (x, y, z) is read as (W, H, D) = (z, y, x)
            self.volume = torch.as_tensor(table.T.reshape(1, table.shape[1], *grid.fine.dims), dtype=dtype).contiguous()
        else:
            self.row = torch.as_tensor(grid.row.astype(np.int64))
            self.fine = torch.as_tensor(fine, dtype=dtype)
            self.coarse = torch.as_tensor(coarse, dtype=dtype)

    def _cells(self, points: torch.Tensor, level: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Lowest node (N, 3), corner flat ids (N, 8), trilinear weights (N, 8) (``Grid.cells``)."""
        h, dims, strides = self.levels[level]
        u = torch.minimum(torch.clamp((points - self.origin) / h, min=0.0), (dims - 1).to(points.dtype))
        i0 = torch.minimum(u.detach().floor().long(), dims - 2)
        t = u - i0
        a = torch.stack([1.0 - t, t], 1)  # (N, 2, 3)
        w = (a[:, :, None, None, 0] * a[:, None, :, None, 1] * a[:, None, None, :, 2]).reshape(len(u), 8)
        return i0, (i0 @ strides)[:, None] + self.corners @ strides, w

    def _coarse(self, points: torch.Tensor) -> torch.Tensor:
        _, idx, w = self._cells(points, "coarse")
        return (w[..., None] * self.coarse[idx]).sum(1)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N, C)."""
        if self.volume is not None:
            g = 2.0 * (points - self.origin) / self.extent - 1.0
            out = torch.nn.functional.grid_sample(self.volume, g.flip(-1).reshape(1, 1, 1, -1, 3), mode="bilinear",
                                                  padding_mode="border", align_corners=True)
            return out.reshape(self.volume.shape[1], -1).T
        i0, idx, w = self._cells(points, "fine")
        rows = self.row[idx]
        vals = self.fine[rows.clamp(min=0)]  # (N, 8, C), constants
        off = rows < 0
        if bool(off.any()):
            n, c = torch.nonzero(off, as_tuple=True)
            corner = self.origin + self.levels["fine"][0] * (i0[n] + self.corners[c]).to(points.dtype)
            vals = vals.clone()
            vals[n, c] = self._coarse(corner)
        return (w[..., None] * vals).sum(1)


class CanonicalBody:
    """The diffused body's fields for one body shape beta, in torch (eq. 6.4-6.8): W~ and the
    SDF from the diffused body's skin tables, B~s(., beta) from its offsets contracted for this
    body (``DiffusedBody.offsets``)."""

    def __init__(self, diffused: DiffusedBody, rest_vertices: np.ndarray, dtype: torch.dtype = torch.float64):
        offsets = diffused.offsets(rest_vertices)
        self.skin = TorchBandGrid(diffused.grid, diffused.skin["fine"], diffused.skin["coarse"], dtype=dtype)
        self.offsets = TorchBandGrid(diffused.grid, offsets.fine, offsets.coarse, dtype=dtype)
        self.bone_index = torch.as_tensor(diffused.bone_index)

    def fields(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """W~(X) (V, K) over the kept bones ``bone_index`` (rows summing to 1), SDF(X) (V,) m,
        B~s(X, beta) (V, 3) m."""
        s = self.skin(X)
        w = torch.clamp(s[:, :-1], min=0.0)
        w = w / torch.clamp(w.sum(-1, keepdim=True), min=1e-12)
        return w, s[:, -1], self.offsets(X)

    def pose(self, X: torch.Tensor, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """M_G (eq. 6.7) of X (V, 3) under skinning transforms (J, 4, 4); returns the posed
        garment (V, 3), T_G(X, beta) (V, 3) and SDF(X) (V,)."""
        w, sdf, offsets = self.fields(X)
        shaped = X + offsets
        A = torch.einsum("vj,jab->vab", w, transforms[self.bone_index, :3, :])  # (V, 3, 4) blended transforms
        posed = torch.einsum("vab,vb->va", A[:, :, :3], shaped) + A[:, :, 3]
        return posed, shaped, sdf

    def unpose(self, x: torch.Tensor, X_fields: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
        """Inverse of eq. 6.7 with the fields frozen at X_fields (V, 3): the start of a solve."""
        w, _, offsets = self.fields(X_fields)
        A = torch.einsum("vj,jab->vab", w, transforms[self.bone_index, :3, :])
        shaped = torch.linalg.solve(A[:, :, :3], (x - A[:, :, 3])[..., None])[..., 0]
        return shaped - offsets


@dataclass(frozen=True)
class ProjectionSettings:
    """Weights of eq. 6.9 and the solver's budget."""

    # E_strain is unitless, E_rec m^2: |G| = 0.1 on every triangle costs as (1 mm)^2 of error on every
    # vertex. Chosen on the validation walk (02_02, T-shirt, 3 frames): 1e-3 left 3.3 mm RMS of
    # error, 1e-5 gave 1.1 mm but |G| 0.31 RMS in the canonical garment; 1e-4: 1.8 mm, |G| 0.19
    w_strain: float = 1e-4
    w_collision: float = 1e-2  # per metre of depth below eps: a vertex 1 mm inside costs as (3 mm)^2 of error
    eps_m: float = 2e-3  # the canonical garment keeps this clearance from the canonical body
    w_posed: float = 0.0  # E_posed's weight (0: off), per metre as w_collision
    eps_posed_m: float = 2e-3  # the posed garment's clearance from the simulation's body
    iterations: int = 60  # L-BFGS iterations per frame
    first_frame_iterations: int = 200


@dataclass
class FrameReport:
    """Convergence of one frame: reconstruction error of M_G(X*) against the target (mm), strain
    of T_G(X*) (RMS |G|_F over triangles), X* vertices inside the canonical body and within eps
    of it (shares), the solver's iterations and seconds, and (with E_posed) the share of the posed
    garment behind the body."""

    rec_rms_mm: float
    rec_max_mm: float
    strain_rms: float
    inside: float
    within_eps: float
    energy: float
    iterations: int
    seconds: float
    posed_inside: float = 0.0  # share of M_G(X*) behind its contact's body normal (with E_posed)


def _strain_rms(cloth: ClothGeometry, shaped: torch.Tensor) -> torch.Tensor:
    """Area-weighted mean of |G|_F^2 over triangles (eq. 6.11), unitless."""
    F = deformation_gradients(shaped[None], cloth.faces, cloth.dm_inv)[0]
    C = torch.einsum("fci,fcj->fij", F, F)
    G = 0.5 * (C - torch.eye(2, dtype=C.dtype))
    g2 = (G * G).sum((-1, -2))
    return (g2 * cloth.rest_area_m2).sum() / cloth.rest_area_m2.sum()


class Projector:
    """Solves eq. 6.9 for the frames of one garment on one body (module docstring)."""

    def __init__(self, body: CanonicalBody, cloth: ClothGeometry, settings: ProjectionSettings = ProjectionSettings()):
        self.body, self.cloth, self.settings = body, cloth, settings

    def terms(self, X: torch.Tensor, target: torch.Tensor, transforms: torch.Tensor,
              contact: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        posed, shaped, sdf = self.body.pose(X, transforms)
        out = {
            "rec": ((posed - target) ** 2).sum(-1).mean(),
            "strain": _strain_rms(self.cloth, shaped),
            "collision": torch.clamp(self.settings.eps_m - sdf, min=0.0).mean(),
            "posed": posed, "sdf": sdf,
        }
        if contact is not None:
            b, n = contact
            out["posed_collision"] = torch.clamp(self.settings.eps_posed_m - ((posed - b) * n).sum(-1), min=0.0).mean()
        return out

    def energy(self, t: dict[str, torch.Tensor]) -> torch.Tensor:
        s = self.settings
        e = t["rec"] + s.w_strain * t["strain"] + s.w_collision * t["collision"]
        return e + s.w_posed * t["posed_collision"] if "posed_collision" in t else e

    def frame(self, target: torch.Tensor, transforms: torch.Tensor, X0: torch.Tensor, iterations: int,
              contact: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, FrameReport]:
        """One frame: X* from X0 (V, 3); target (V, 3) posed; transforms (J, 4, 4); contact: the
        posed body's vertex nearest each target vertex and its normal ((V, 3), (V, 3)) for E_posed."""
        t0 = time.perf_counter()
        X = X0.detach().clone().requires_grad_(True)
        opt = torch.optim.LBFGS([X], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-12, tolerance_change=1e-15)

        def closure():
            opt.zero_grad()
            e = self.energy(self.terms(X, target, transforms, contact))
            e.backward()
            return e

        opt.step(closure)
        with torch.no_grad():
            t = self.terms(X, target, transforms, contact)
            err = torch.linalg.norm(t["posed"] - target, dim=-1)
            report = FrameReport(
                rec_rms_mm=float(torch.sqrt((err ** 2).mean())) * 1e3, rec_max_mm=float(err.max()) * 1e3,
                strain_rms=float(torch.sqrt(t["strain"])), inside=float((t["sdf"] < 0).double().mean()),
                within_eps=float((t["sdf"] < self.settings.eps_m).double().mean()), energy=float(self.energy(t)),
                iterations=int(opt.state[opt._params[0]]["n_iter"]), seconds=time.perf_counter() - t0,
                posed_inside=0.0 if contact is None else float((((t["posed"] - contact[0]) * contact[1]).sum(-1) < 0).double().mean()))
        return X.detach(), report

    def sequence(self, targets: np.ndarray, transforms: np.ndarray, template: np.ndarray,
                 bodies: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, list[FrameReport]]:
        """Canonical frames X* (T, V, 3) float32 of posed targets (T, V, 3) under transforms
        (T, J, 4, 4), warm-started frame to frame from the unposed first frame. bodies: the
        simulation's posed body vertices (T, Vb, 3) and faces (F, 3), needed for E_posed."""
        dtype = self.cloth.dm_inv.dtype
        tg = torch.as_tensor(np.asarray(targets), dtype=dtype)
        tf = torch.as_tensor(np.asarray(transforms), dtype=dtype)
        contacts = [None] * len(tg)
        if self.settings.w_posed > 0:
            if bodies is None:
                raise ValueError("E_posed needs the simulation's posed bodies")
            contacts = posed_contacts(np.asarray(targets), *bodies, dtype)
        X = self.body.unpose(tg[0], torch.as_tensor(np.asarray(template), dtype=dtype), tf[0])
        out, reports = [], []
        for f in range(len(tg)):
            X, r = self.frame(tg[f], tf[f], X, self.settings.first_frame_iterations if f == 0 else self.settings.iterations, contacts[f])
            out.append(X.numpy().astype(np.float32))
            reports.append(r)
        return np.stack(out), reports


def posed_contacts(targets: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray,
                   dtype: torch.dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per frame, the posed body's vertex nearest each target vertex and its unit normal
    (E_posed's b and n): targets (T, V, 3), body_vertices (T, Vb, 3) -> T pairs of (V, 3)."""
    import scipy.spatial

    from inference.mesh import vertex_normals

    normals = vertex_normals(np.asarray(body_vertices, np.float32), body_faces)
    out = []
    for x, b, n in zip(targets, body_vertices, normals):
        nn = scipy.spatial.cKDTree(b).query(x)[1]
        out.append((torch.as_tensor(b[nn], dtype=dtype), torch.as_tensor(n[nn], dtype=dtype)))
    return out


def summarise(reports: list[FrameReport]) -> dict:
    """Means over frames, and the worst frame's values, of a sequence's reports."""
    rows = [asdict(r) for r in reports]
    keys = rows[0].keys()
    return {"frames": len(rows), "mean": {k: float(np.mean([r[k] for r in rows])) for k in keys},
            "max": {k: float(np.max([r[k] for r in rows])) for k in keys}}


def reference_transforms(body, metadata: dict) -> tuple[np.ndarray, np.ndarray]:
    """Skinning transforms (T, J, 4, 4) of a reference simulation's frames and its body's rest
    vertices (Vb, 3), from its metadata (``training.reference.simulate_case``)."""
    from training.protocol import BODIES, Case, case_motion

    case = Case(metadata["clip"], metadata["body"], int(metadata["start"]), int(metadata["frames"]))
    shape, motion, start = case_motion(body, case)
    window = slice(start, start + case.frames)
    _, transforms = body.pose(shape.rest_bone_poses, motion.rotations[None, window], motion.translation[None, window])
    return transforms[0], shape.rest_vertices[0]


def main(argv: list[str] | None = None) -> None:
    import argparse
    import json
    import logging
    from pathlib import Path

    from inference.body import BodyModel
    from inference.garment import GarmentCatalog

    p = argparse.ArgumentParser(description="Project reference simulations into the canonical space (thesis eq. 6.9).")
    p.add_argument("references", nargs="+", type=Path, help="reference .npz files (training.reference)")
    p.add_argument("--diffused", type=Path, default=DEFAULT_PATH, help="diffused body (python -m training.assets.build_diffused_body)")
    p.add_argument("--out-dir", type=Path, default=Path("build/canonical"))
    p.add_argument("--frames", type=int, default=None, help="first frames only")
    p.add_argument("--w-strain", type=float, default=ProjectionSettings.w_strain)
    p.add_argument("--w-collision", type=float, default=ProjectionSettings.w_collision)
    p.add_argument("--iterations", type=int, default=ProjectionSettings.iterations)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    log = logging.getLogger("training.projection")
    body, catalog, diffused = BodyModel.load(), GarmentCatalog.load(), DiffusedBody.load(args.diffused)
    settings = ProjectionSettings(w_strain=args.w_strain, w_collision=args.w_collision, iterations=args.iterations)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for path in args.references:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["metadata"]))
            targets = f["vertices"][: args.frames]
        asset = catalog.get(meta["garment"])
        transforms, rest = reference_transforms(body, meta)
        projector = Projector(CanonicalBody(diffused, rest), ClothGeometry.from_asset(asset), settings)
        X, reports = projector.sequence(targets, transforms[: len(targets)], asset.vertices)
        report = {"reference": path.name, "settings": asdict(settings), **summarise(reports)}
        out = args.out_dir / path.name
        np.savez_compressed(out, canonical=X, report=np.str_(json.dumps(report)), frame_reports=np.str_(json.dumps([asdict(r) for r in reports])))
        log.info("%s: %s", out, json.dumps(report))


if __name__ == "__main__":
    main()
