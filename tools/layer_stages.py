"""Where the layer order of T-shirt under jacket (both fit 'canonical') is lost, stage by stage, on
the validation clip (02_02 frames 30-50): % of T-shirt vertex-frames beyond the jacket
(``inference.metrics.layer_violation_pct``) and intersecting triangle pairs per frame
(``inference.intersections``) in the canonical space, shaped in the rest pose (eq. 6.8), posed
(eq. 6.7, the arms as the clip has them) and after the body's exact repair; then the same with the
jacket skinned by the T-shirt's weights where it lies within 2-5 cm of it (a layer-consistent
skinning: if the weights were what breaks the order, this would keep it).

    python tools/layer_stages.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel, linear_blend_skinning  # noqa: E402
from inference.canonical import default_canonical  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.intersections import layer_intersections  # noqa: E402
from inference.metrics import layer_violation_pct, unsigned_distance  # noqa: E402
from inference.repair import repair_layers  # noqa: E402
from training.protocol import BODIES, clip_motion, load_clip  # noqa: E402

# The jacket takes the T-shirt's weights within NEAR of it, its own beyond FAR, blended between.
NEAR_M, FAR_M = 0.02, 0.05


def inner_weights(X_outer: np.ndarray, X_inner: np.ndarray, inner_faces: np.ndarray, W_inner: np.ndarray,
                  W_outer: np.ndarray) -> np.ndarray:
    """The outer layer's weights blended towards the inner layer's at its closest inner point."""
    _, fi, c = unsigned_distance(X_outer[None], X_inner[None], inner_faces)
    fi, c = fi[0], c[0]
    tri = X_inner[inner_faces[fi]].astype(np.float64)
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], c - tri[:, 0]
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-30)
    b, g = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1 - b - g, b, g], 1), 0, 1)
    bary /= bary.sum(1, keepdims=True)
    w_in = np.einsum("nk,nkj->nj", bary, W_inner[inner_faces[fi]])
    a = np.clip((FAR_M - np.linalg.norm(X_outer - c, axis=1)) / (FAR_M - NEAR_M), 0, 1)[:, None]
    return (a * w_in + (1 - a) * W_outer).astype(np.float32)


def main() -> None:
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    can = default_canonical()
    T, J = catalog.get("tshirt"), catalog.get("jacket")
    XT, XJ = can.template(T), can.template(J)

    def report(label: str, t: np.ndarray, j: np.ndarray) -> str:
        return f"{label} {layer_violation_pct(t[None], j[None], J.faces):.2f} % / {layer_intersections(t, T.faces, j, J.faces).mean():.0f}"

    clip = load_clip("02_02", body)
    print("% beyond / intersecting pairs per frame, T-shirt under jacket, both canonical")
    for name in ("neutral", "heavy", "light-tall"):
        shape = body.shape(BODIES[name][None])
        m = clip_motion(body, shape, clip, 50)
        _, tr = body.pose(shape.rest_bone_poses, m.rotations[None, 30:], m.translation[None, 30:])
        bv = body.skin(shape.rest_vertices, tr)
        st, wt = can.rest_fit(T, shape.rest_vertices[0])
        sj, wj = can.rest_fit(J, shape.rest_vertices[0])
        pt = linear_blend_skinning(st[None, None].repeat(20, 1), wt, tr)
        pj = linear_blend_skinning(sj[None, None].repeat(20, 1), wj, tr)
        (rt, rj), _ = repair_layers([pt, pj], bv, body.faces, [0.002, 0.006])
        pj2 = linear_blend_skinning(sj[None, None].repeat(20, 1), inner_weights(XJ, XT, T.faces, wt, wj), tr)
        print(f"{name:10s}: {report('canonical', XT[None], XJ[None])} | {report('shaped', st[None], sj[None])} | "
              f"{report('posed', pt[0], pj[0])} | {report('repaired', rt[0], rj[0])} | "
              f"{report('posed, jacket on the T-shirt weights', pt[0], pj2[0])}", flush=True)


if __name__ == "__main__":
    main()
