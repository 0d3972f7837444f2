"""Why a canonical garment ends inside the posed body before the final stage: its static form X
(the template pushed to its margin) posed by eq. 6.7 with other skinning fields than the shipped
ones, and with a pose clearance added to its margin, on the validation walk.

    python tools/inside_fields.py [--garment tshirt --garment trousers ...] [--clearance]

Per case and garment, % of vertex-frames inside the posed body away from body
self-intersections (``inference.metrics.collision_rates``), with W~ and B~s read

- grid    : as shipped (``inference.diffused``: the 1.5 cm band grid of the diffusion kernels);
- exact   : at X's closest point on the canonical skin, barycentric (libigl): no diffusion;
- coarse  : W~ from the 5 cm coarse grid alone (B~s as shipped): twice the smoothing;

and where the shipped posing leaves them: the canonical distance of those vertices (median and
p10-p90, mm), their posed depth (median, mm) and the bones of their nearest skin vertices.

``--clearance``: the probes 3 mm off every skin vertex along its normal, posed through the
diffused body on the training clips (``training.datasets.TRAIN_CLIPS`` but the BVH one, every 6th
frame, the neutral, heavy and two training bodies), give each skin vertex the p99 over frames of
how far its probe ended short of 1 mm outside the posed skin (capped at 1 cm, dilated twice over
the mesh); X is then pushed to margin + that clearance (read through the diffusion kernels) and
posed again. With ``--learned`` too, the same for the learned canonical garments (X_t from the
regressor and decoder, run from the clip's frame 0 as the judge does, pushed to the margin, the
strain limit after eq. 6.7): inside % without / with the clearance, and how far it moved X_t.
Units: metres inside, mm and % printed.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import igl
import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel, linear_blend_skinning  # noqa: E402
from inference.canonical import PUSH_TOLERANCE_M, CanonicalModels, margin, push_fields, sdf_gradient  # noqa: E402
from inference.diffused import DEFAULT_PATH  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.mesh import vertex_normals  # noqa: E402
from inference.metrics import collision_rates, inside_mask, near_self_intersection, self_intersection_exclusion  # noqa: E402
from training.datasets import BVH_CLIPS, TRAIN_CLIPS  # noqa: E402
from inference.motion.descriptor import motion_descriptor  # noqa: E402
from training.protocol import BODIES, SPLITS, case_motion, clip_motion, load_clip  # noqa: E402

PROBE_M = 0.003
TARGET_M = 0.001
CAP_M = 0.01


def closest_fields(X: np.ndarray, neutral: np.ndarray, faces: np.ndarray, weights: np.ndarray, delta: np.ndarray):
    """W and B~s at X's closest points on the canonical skin (barycentric), no diffusion."""
    V = neutral.astype(np.float64)
    _, tri, cp = igl.signed_distance(X.astype(np.float64), V, faces)[:3]
    f = faces[tri]
    bary = igl.barycentric_coordinates(cp, V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]).astype(np.float32)
    return np.einsum("vk,vkj->vj", bary, weights[f]), np.einsum("vk,vkd->vd", bary, delta[f])


def clearance(body: BodyModel, can: CanonicalModels, weights: np.ndarray) -> np.ndarray:
    """Per skin vertex, the pose clearance (module docstring), metres (V,)."""
    d = can.diffused
    nv, faces = d.neutral_vertices, body.faces.astype(np.int64)
    probes = (nv + PROBE_M * vertex_normals(nv, body.faces)).astype(np.float32)
    rest_sd = igl.signed_distance(probes.astype(np.float64), nv.astype(np.float64), faces)[0]
    outer = rest_sd >= PROBE_M - 0.001  # not the inner parts (eyes, mouth) or the folded toes
    fields = d.fields(probes[None])
    short = []
    for name in ("neutral", "heavy", "train-slim", "train-tall"):
        shape = body.shape(BODIES[name][None])
        offsets = d.offsets(shape.rest_vertices[0])
        for clip_id in (c for c in TRAIN_CLIPS if c not in BVH_CLIPS):
            motion = clip_motion(body, shape, load_clip(clip_id, body))
            idx = np.arange(0, motion.num_frames, 6)
            _, T = body.pose(shape.rest_bone_poses, motion.rotations[None, idx], motion.translation[None, idx])
            skin = body.skin(shape.rest_vertices, T)[0]
            posed = d.pose(np.repeat(probes[None], len(idx), 0), offsets, T[0], np.repeat(fields, len(idx), 0))
            sd = np.stack([igl.signed_distance(posed[i].astype(np.float64), skin[i].astype(np.float64), faces)[0] for i in range(len(idx))])
            sd[self_intersection_exclusion(skin, body.faces)] = np.nan
            short.append(np.maximum(TARGET_M - sd[:, outer], 0.0))
            print(f"  clearance: {name} {clip_id}, {len(idx)} frames", flush=True)
    e = np.zeros(len(nv), np.float32)
    e[outer] = np.minimum(np.nan_to_num(np.nanquantile(np.concatenate(short), 0.99, axis=0)), CAP_M)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    adj = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(nv),) * 2).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float32)
    deg = np.maximum(np.asarray(adj.sum(1)).ravel(), 1.0)
    for _ in range(2):
        e = np.maximum(e, (adj @ e) / deg).astype(np.float32)
    return e


def push_clear(can: CanonicalModels, X: np.ndarray, margin_m: float, e: np.ndarray) -> np.ndarray:
    """X pushed along the canonical SDF's gradient until SDF - clearance >= margin."""
    d = can.diffused
    fine, coarse = d.kernels["fine"].contract(e[:, None]), d.kernels["coarse"].contract(e[:, None])
    X = X.copy()
    for _ in range(8):
        s = d.sdf(X) - d.grid.interpolate(X, fine, coarse)[..., 0]
        low = s < margin_m - PUSH_TOLERANCE_M
        if not low.any():
            break
        X[low] += (margin_m - s[low])[:, None] * sdf_gradient(d, X[low])
    return X


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--garment", action="append")
    p.add_argument("--clearance", action="store_true")
    p.add_argument("--learned", action="store_true", help="with --clearance: the learned canonical garments too")
    args = p.parse_args()
    body, catalog, can = BodyModel.load(), GarmentCatalog.load(), CanonicalModels()
    d = can.diffused
    with np.load(DEFAULT_PATH, allow_pickle=False) as f:
        weights = f["vertex_weights"].astype(np.float32)
    faces = body.faces.astype(np.int64)
    e = clearance(body, can, weights) if args.clearance else None
    tree = cKDTree(d.neutral_vertices)
    for case in SPLITS["validation"]:
        shape = body.shape(BODIES[case.body][None])
        motion = clip_motion(body, shape, load_clip(case.clip, body), case.start + case.frames)
        w = slice(case.start, case.start + case.frames)
        _, T = body.pose(shape.rest_bone_poses, motion.rotations[None, w], motion.translation[None, w])
        skin = body.skin(shape.rest_vertices, T)
        offsets = d.offsets(shape.rest_vertices[0])
        delta = shape.rest_vertices[0] - d.neutral_vertices
        for g in args.garment or ["tshirt", "trousers", "longsleeve", "dress", "jacket"]:
            asset = catalog.get(g)
            X = can.template(asset)
            Wg, Bg = d.weights(X), d.shape_offsets(X, offsets)
            We, Be = closest_fields(X, d.neutral_vertices, faces, weights, delta)
            coarse = np.maximum(d.grid.coarse.interpolate(X, d.skin["coarse"])[..., :-1], 0.0)
            Wc = np.zeros_like(Wg)
            Wc[:, d.bone_index] = coarse / np.maximum(coarse.sum(-1, keepdims=True), 1e-12)
            variants = {"grid": (X, Wg, Bg), "exact": (X, We, Be), "coarse": (X, Wc, Bg)}
            if e is not None:
                Xc = push_clear(can, X, margin(asset), e)
                variants["clearance"] = (Xc, d.weights(Xc), d.shape_offsets(Xc, offsets))
            pct = {}
            for name, (XX, W, B) in variants.items():
                posed = linear_blend_skinning(np.repeat((XX + B)[None, None], case.frames, 1), W, T)
                pct[name] = collision_rates(posed, skin, body.faces)["inside_pct_clean"]
            posed = d.pose(np.repeat(X[None], case.frames, 0), offsets, T[0])
            inside = inside_mask(posed, skin[0], body.faces) & ~near_self_intersection(posed, skin[0], body.faces)
            t, v = np.nonzero(inside)
            where = ""
            if len(v):
                sdc = 1e3 * d.sdf(X[v])
                pick = np.linspace(0, len(v) - 1, min(len(v), 200)).astype(int)
                depth = [-1e3 * igl.signed_distance(posed[t[i], v[i]][None].astype(np.float64), skin[0, t[i]].astype(np.float64), faces)[0][0]
                         for i in pick]
                bones, counts = np.unique(weights[tree.query(X[v])[1]].argmax(1), return_counts=True)
                top = sorted(zip(counts, bones), reverse=True)[:3]
                where = (f" | canonical distance {np.median(sdc):.1f} mm ({np.quantile(sdc, 0.1):.1f}-{np.quantile(sdc, 0.9):.1f}), "
                         f"depth {np.median(depth):.1f} mm, near " + ", ".join(f"{body.bone_names[b]} {c}" for c, b in top))
            print(f"{case.name:22s} {g:10s} " + " ".join(f"{k} {v:.3f} %" for k, v in pct.items()) + where, flush=True)
        if e is not None and args.learned:
            learned_clearance(body, can, catalog, case, e, [g for g in args.garment or ["tshirt", "trousers", "longsleeve", "dress"]
                                                           if can.available(g)])


def learned_clearance(body, can, catalog, case, e, garments) -> None:
    """``--learned``: the learned canonical garments without / with the clearance (module docstring)."""
    d = can.diffused
    shape, motion, start = case_motion(body, case)
    _, T = body.pose(shape.rest_bone_poses, motion.rotations[None], motion.translation[None])
    T = T[0, start:]
    skin = body.skin(shape.rest_vertices, T[None])
    offsets = d.offsets(shape.rest_vertices[0])
    gamma = motion_descriptor(motion.rotations[None], motion.translation[None], motion.fps)
    for g in garments:
        asset = catalog.get(g)
        X, _ = can.frames(asset, shape.phenotypes, gamma, [motion.num_frames], push=False)
        X0 = push_fields(d, X[start:], margin(asset))[0]
        X1 = push_clear(can, X0.reshape(-1, 3), margin(asset), e).reshape(X0.shape)
        pct = [collision_rates(can.strain_limit(asset)(d.pose(XX, offsets, T))[None], skin, body.faces)["inside_pct_clean"] for XX in (X0, X1)]
        moved = np.linalg.norm(X1 - X0, axis=-1)
        print(f"{case.name:22s} {g:10s} learned: inside {pct[0]:.3f} -> {pct[1]:.3f} % with the clearance; it moved "
              f"{100 * (moved > 1e-4).mean():.1f} % of the vertex-frames, at most {1e3 * moved.max():.1f} mm", flush=True)


if __name__ == "__main__":
    main()
