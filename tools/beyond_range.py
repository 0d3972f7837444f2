"""Measurements behind the beyond-range defaults (docs/benchmarks.md, "Beyond the body range").

    python tools/beyond_range.py variants --split bodies --garment tshirt --garment longsleeve --garment dress
    python tools/beyond_range.py variants --split bodies --garment crewtee:tshirt --garment shirt:tshirt   # carried residual
    python tools/beyond_range.py variants --split bodies --garment crewtee:tshirt --smooth 30
    python tools/beyond_range.py edge        # the default's step across the edge of the body range
    python tools/beyond_range.py cost        # CPU per garment-frame: within, in the blend band, beyond
    python tools/beyond_range.py means       # test bodies: the static form against the beyond-range defaults

variants: each other way of giving a body beyond the range a one-size fit, against newton on a
protocol split (error cm, % of vertices inside the posed body before the final stage, % of
vertex-frames the final stage moved, edge p1 / p99, folded faces %, hinge RMS deg), every one
posed as fit 'canonical' is (its rest fit replaced, ``Variants.rest_fit``):
  static      X + B~s(X, beta), the static canonical form
  regressor   U = retarget_fit(beta) + R_G(beta), W~ at the static X (fit 'learned-canonical')
  residual    X + B~s(X, beta) + R_G(beta)
  projected   U taken to the canonical space, X' = U - B~s(X', beta) (two fixed-point steps),
              pushed out to the margin there and posed with W~(X')
  pushed      U moved only by that push, W~ at the static X
  relaxed     the static form relaxed toward its rest lengths: ROUNDS rounds of the strain
              limit's stretch side at RELAX_RATIO, each pushed out of the shaped body along the
              nearest body vertex's normal
  carried     (garment:donor) the donor's R_G residual carried to the garment by its 4 nearest
              template vertices (inverse-distance weights; ``--smooth N``: then N passes of half a
              uniform Laplacian step on the garment's mesh), on the garment's own retarget fit
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.canonical import BODY_RANGE_BY_CATEGORY, CanonicalModels, margin, push_out  # noqa: E402
from inference.learned import default_models  # noqa: E402
from inference.mesh import vertex_normals  # noqa: E402
from inference.metrics import realism  # noqa: E402
from inference.motion.clips import ClipLibrary  # noqa: E402
from inference.pipeline import DrapeOptions, PoseSequence, drape  # noqa: E402
from inference.strain import StrainLimit  # noqa: E402
from training.judge import REFERENCE, Inputs, _collisions, mean_error_cm  # noqa: E402
from training.protocol import SPLITS, case_motion  # noqa: E402
from training.reference import REFERENCE_DIR, reference_path  # noqa: E402

RELAX_RATIO = 1.05
ROUNDS = 80
CARRY_NEIGHBOURS = 4


class Variants(CanonicalModels):
    """Canonical models whose static rest fit is replaced by ``variant`` (module docstring)."""

    variant = "static"
    U = None  # the fit regressor's (or the carried) garment on the shaped body, (V, 3)
    R0 = None  # the garment's retarget fit on the shaped body, (V, 3)
    body_faces = None

    def rest_fit(self, garment, rest_vertices):
        u, W = super().rest_fit(garment, rest_vertices)
        if self.variant == "static":
            return u, W
        if self.variant in ("regressor", "carried"):
            return self.U.astype(np.float32), W
        if self.variant == "residual":
            return (u + self.U - self.R0).astype(np.float32), W
        if self.variant in ("projected", "pushed"):
            d, (_, W0, S) = self.diffused, self._static(garment)
            offsets = d.offsets(rest_vertices)
            Xp = (self.U - S @ (np.asarray(rest_vertices, np.float32) - d.neutral_vertices)).astype(np.float32)
            Xp = (self.U - d.shape_offsets(Xp, offsets)).astype(np.float32)
            Xq = push_out(d, Xp, margin(garment))[0]
            if self.variant == "projected":
                return d.deshaped_to_shaped(Xq, offsets), d.weights(Xq)
            return (self.U + d.deshaped_to_shaped(Xq, offsets) - d.deshaped_to_shaped(Xp, offsets)).astype(np.float32), W0
        if self.variant == "relaxed":
            B = np.asarray(rest_vertices, np.float64)
            N = vertex_normals(B[None].astype(np.float32), self.body_faces)[0].astype(np.float64)
            tree, limit, m = cKDTree(B), StrainLimit.from_mesh(garment.rest_vertices, garment.edges, 0.8, RELAX_RATIO), margin(garment)
            U = u.astype(np.float64)
            for _ in range(ROUNDS):
                U = limit(U[None].astype(np.float32), iterations=5)[0].astype(np.float64)
                _, j = tree.query(U)
                s = ((U - B[j]) * N[j]).sum(-1)
                low = s < m
                U[low] += (m - s[low])[:, None] * N[j[low]]
            return U.astype(np.float32), W
        raise ValueError(self.variant)


def neighbours(garment) -> scipy.sparse.csr_matrix:
    """(V, V) row-normalised adjacency of the garment's mesh: the mean of each vertex's neighbours."""
    e, V = garment.edges, len(garment.template)
    A = scipy.sparse.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(V, V)).tocsr()
    return (scipy.sparse.diags(1.0 / np.maximum(np.asarray(A.sum(1)).ravel(), 1)) @ A).tocsr()


def variants(args) -> None:
    inputs = Inputs.load()
    body, models, canon = inputs.body, default_models(), Variants()
    canon.body_faces = body.faces
    names = args.variant or ["static", "regressor", "residual", "projected", "pushed", "relaxed"]
    print("| garment | case | variant | error cm | inside % before | moved % | edge p1 | edge p99 | folded % | rough deg |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for split in args.split:
        for case in SPLITS[split]:
            shape, motion, start = case_motion(body, case)
            m = PoseSequence(motion.rotations[start:start + case.frames], motion.translation[start:start + case.frames], motion.fps)
            hm08 = body.hm08_vertices(shape)
            for spec in args.garment:
                gid, _, donor = spec.partition(":")
                path = reference_path(gid, case.key, REFERENCE, REFERENCE_DIR)
                if not path.exists():
                    continue
                with np.load(path, allow_pickle=False) as f:
                    ref = f["vertices"]
                g = inputs.catalog.get(gid)
                canon.R0 = g.retarget_fit(hm08)[0]
                if donor:
                    dg = inputs.catalog.get(donor)
                    R = models.get(donor, "/options/fit").fit(shape.phenotypes)[0]
                    dist, nn = cKDTree(dg.template).query(g.template, k=CARRY_NEIGHBOURS)
                    w = 1.0 / np.maximum(dist, 1e-4)
                    w /= w.sum(1, keepdims=True)
                    carried = (R[nn] * w[..., None]).sum(1)
                    for _ in range(args.smooth):  # half a uniform Laplacian step on the garment's mesh
                        carried = 0.5 * carried + 0.5 * (neighbours(g) @ carried)
                    canon.U = canon.R0 + carried
                    run = ["static", "carried"]
                else:
                    canon.U = canon.R0 + models.get(gid, "/options/fit").fit(shape.phenotypes)[0]
                    run = names
                for variant in run:
                    canon.variant = variant
                    options = DrapeOptions(fit="canonical", dynamics="none", lift_arms=False)
                    after = drape(body, shape, m, [g], options, canonical=canon)
                    before = drape(body, shape, m, [g], options.replace(collisions="off"), canonical=canon)
                    v, v0 = after.garments[0].vertices, before.garments[0].vertices
                    r = realism(v, g.faces, g.rest_vertices, g.edges)
                    inside = _collisions(v0, after.body_vertices, body.faces)["inside_pct_clean"]
                    moved = 100.0 * float((np.linalg.norm(v - v0, axis=-1) > 1e-4).mean())
                    label = f"{variant} ({donor})" if variant == "carried" else variant
                    print(f"| {gid} | {case.name} | {label} | {mean_error_cm(v, ref):.2f} | {inside:.2f} | {moved:.1f} | {r['edge_p1']:.2f} | "
                          f"{r['edge_p99']:.2f} | {r['folded_pct']:.2f} | {r['roughness_deg']:.1f} |", flush=True)


def _walk(frames: int) -> PoseSequence:
    clip = ClipLibrary().load("walk")
    return PoseSequence(clip.rotations[:frames], clip.translation[:frames], clip.fps)


def canon_beyond(garment_id: str) -> tuple[str, str]:
    """(fit, dynamics) the shipped defaults run beyond the garment's range."""
    from inference.defaults import default_methods

    b = default_methods().get(garment_id).beyond_range
    return (b.fit, b.dynamics) if b is not None else ("canonical", "none")


def edge(args) -> None:
    """The default drape of bodies 0.02 apart in phenotype space, lighter than the T-shirt's first
    training body (the neutral one), across each garment's range and at the blend band's ends."""
    inputs = Inputs.load()
    body, canon, motion = inputs.body, CanonicalModels(), _walk(10)
    lighter = np.array([0, 0, 0, -1, 0, 0], np.float32)
    print("| garment | collisions | distance a -> b | weight a -> b | mean step cm | p99 cm | max cm |")
    print("|---|---|---|---|---|---|---|")
    for gid in ("tshirt", "longsleeve", "dress"):
        g = inputs.catalog.get(gid)
        r = BODY_RANGE_BY_CATEGORY.get(g.category, 0.1)
        base = canon.train_phenotypes(gid)[0]
        beyond = canon_beyond(gid)
        a, b = r - 0.01, r + 0.01  # a hard switch at the range (as before the blend): the learned model, then the beyond-range method
        out = [drape(body, body.shape((base + d * lighter)[None]), motion, [g], DrapeOptions(lift_arms=False, fit=f, dynamics=dy), canonical=canon).garments[0]
               for d, (f, dy) in ((a, ("canonical", "learned")), (b, beyond))]
        step = np.linalg.norm(out[1].vertices - out[0].vertices, axis=-1)
        print(f"| {gid} | exact, hard switch | {a:.2f} -> {b:.2f} | 0 -> 1 | {100 * step.mean():.2f} | {100 * np.quantile(step, 0.99):.2f} | "
              f"{100 * step.max():.1f} |", flush=True)
        steps = [(r - 0.01, r + 0.01)] + ([(0.26, 0.28), (0.10, 0.12)] if gid == "tshirt" else [])
        for a, b in steps:
            for collisions, opts in (("exact", {}), ("off, learned only", {"collisions": "off", "fit": "canonical", "dynamics": "learned"})):
                if collisions != "exact" and gid != "tshirt":
                    continue
                out = []
                for d in (a, b):
                    res = drape(body, body.shape((base + d * lighter)[None]), motion, [g], DrapeOptions(lift_arms=False, **opts), canonical=canon)
                    out.append(res.garments[0])
                step = np.linalg.norm(out[1].vertices - out[0].vertices, axis=-1)
                w = [canon.beyond_weight(g, base + d * lighter) for d in (a, b)]
                print(f"| {gid} | {collisions} | {a:.2f} -> {b:.2f} | {w[0]:.2f} -> {w[1]:.2f} | {100 * step.mean():.2f} | "
                      f"{100 * np.quantile(step, 0.99):.2f} | {100 * step.max():.1f} |", flush=True)


def cost(args) -> None:
    """CPU per garment-frame through the runtime (one request of 31 frames of 'dance', the T-shirt,
    no body in the answer; median of 7 after 2), on the T-shirt's first training body, in its blend
    band and beyond its range."""
    from inference.body import PHENOTYPE_LABELS
    from service.config import Settings
    from service.runtime import Runtime
    from service.schemas import DrapeRequest

    rt = Runtime.load(Settings())
    base = rt.canonical.train_phenotypes("tshirt")[0]
    lighter = np.array([0, 0, 0, -1, 0, 0], np.float32)
    print("| body | method | ms CPU per garment-frame | of which the final stage |")
    print("|---|---|---|---|")
    for name, d in (("training body", 0.0), ("in the band", 0.34), ("beyond", 0.5)):
        request = DrapeRequest.model_validate({
            "body": {"phenotypes": dict(zip(PHENOTYPE_LABELS, (base + d * lighter).tolist()))},
            "motion": {"type": "clip", "clip": "dance", "start_s": 1.0, "duration_s": 1.0},
            "garments": [{"id": "tshirt"}], "format": "npz", "options": {"include_body": False}})
        for _ in range(2):
            out = rt.run_drape(request)
        ts = []
        for _ in range(7):
            t0 = time.process_time()
            out = rt.run_drape(request)
            ts.append(time.process_time() - t0)
        frames = int(out.headers["X-Frames"])
        print(f"| {name} ({d:.2f}) | {out.model_versions['fit']['tshirt']} | {1e3 * np.median(ts) / frames:.2f} | "
              f"{out.timings_ms['repair'] / frames:.2f} |", flush=True)


def means(args) -> None:
    """Mean error from newton over the garments whose default is the learned canonical model, per
    test body beyond every range: the static canonical form against the shipped beyond-range
    defaults, from the judge's rows (``--json`` of the two judge commands, docs/evaluation*.md)."""
    import json

    from inference.defaults import default_methods

    from inference.garment import GarmentCatalog
    from training.protocol import BODIES

    table, canon, catalog = default_methods(), CanonicalModels(), GarmentCatalog.load()
    rows = [r for f in args.json for r in json.loads(Path(f).read_text())["results"].get("test", [])]
    rows = [r for r in rows if canon.beyond_weight(catalog.get(r["garment"]), BODIES[r["body"]]) >= 1.0]  # beyond the range
    for body in sorted({r["body"] for r in rows}):
        static, default = [], []
        for r in rows:
            e = table.get(r["garment"])
            if r["body"] != body or e.method != e.method.__class__("canonical", "learned"):
                continue
            fit, dyn = canon_beyond(r["garment"])
            name = "learned-canonical" if fit == "learned-canonical" else "canonical" if dyn == "none" else "canonical-learned"
            static.append(r["methods"]["canonical"]["error_cm"])
            default.append(r["methods"][name]["error_cm"])
        print(f"{body}: {len(static)} garments, static canonical {np.mean(static):.2f} cm, beyond-range defaults {np.mean(default):.2f} cm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    v = sub.add_parser("variants")
    v.add_argument("--split", action="append", choices=sorted(SPLITS), required=True)
    v.add_argument("--garment", action="append", required=True, help="garment id, or garment:donor for the carried residual")
    v.add_argument("--smooth", type=int, default=0, help="carried residual: passes of half a Laplacian step")
    v.add_argument("--variant", action="append", choices=["static", "regressor", "residual", "projected", "pushed", "relaxed"])
    sub.add_parser("edge")
    sub.add_parser("cost")
    mn = sub.add_parser("means")
    mn.add_argument("--json", action="append", default=None, help="the judge's raw results (default: both of build/judge/)")
    args = ap.parse_args()
    if args.command == "means" and not args.json:
        args.json = ["build/judge/results.json", "build/judge/catalog.json"]
    {"variants": variants, "edge": edge, "cost": cost, "means": means}[args.command](args)


if __name__ == "__main__":
    main()
