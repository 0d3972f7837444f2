"""Garments and outfits on motions the project does not use, through the service's own path: a
search for failures, not a split to choose anything on.

    python tools/motion_sweep.py --mocap-dir ../shared/data/mocap/cmu-asfamc --window 02_06:3:4 \
        [--window 01_12:10:4 ...] [--bvh ../shared/data/mocap/bvh/131_01.bvh:2:4 ...] \
        [--body heavy ...] [--garments tshirt,jacket ...] [--lbs] > sweep.jsonl

Each window (CMU clip id : start s : duration s) of ``<mocap-dir>/<subject>/<clip>.amc`` with the
subject's ASF becomes an ASF/AMC drape request, and each ``--bvh`` window (file : start s :
duration s) a BVH request of those frames (``service.schemas.DrapeRequest``, 30 fps, the default
options), run by ``Runtime.prepare`` + ``drape_batch``, for every body and garment set. One
JSON line per drape:
- per garment: its method, whether every vertex is finite, the % of vertex-frames inside the
  body (``inference.metrics.inside_mask``; the final stage leaves none), the largest edge
  stretch over the template and the share of edge-frames past 2x, the largest and p99.9
  vertex step between frames (cm);
- per pair of consecutive layers: the % of inner vertex-frames beyond the outer layer
  (``inference.metrics.layer_beyond_pct``) and the intersecting triangle pairs per frame.
``--lbs`` adds the same request with fit 'retarget', no dynamics and no collision stage (the
plain skinning baseline) for each drape, to compare stretch and steps against.

Bodies: ``training.protocol.BODIES`` by name, or six phenotypes in [0, 1] (gender, age >= 0.77,
muscle, weight, height, proportions) joined by commas.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.intersections import layer_intersections  # noqa: E402
from inference.mesh import mesh_edges  # noqa: E402
from inference.metrics import inside_mask, layer_beyond_pct  # noqa: E402
from service.config import Settings  # noqa: E402
from service.runtime import Runtime  # noqa: E402
from service.schemas import DrapeRequest  # noqa: E402
from training.protocol import BODIES  # noqa: E402

PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")
AMC_FPS = 120.0  # CMU's capture rate (AMC files do not say)


def amc_window(text: str, start_s: float, duration_s: float) -> str:
    """The AMC frames from start_s for duration_s (renumbered from 1), with the file's header."""
    head, frames = [], []
    for line in text.splitlines():
        if line.strip().isdigit():
            frames.append([])
        elif frames:
            frames[-1].append(line)
        else:
            head.append(line)
    a, b = int(start_s * AMC_FPS), int((start_s + duration_s) * AMC_FPS)
    out = list(head)
    for i, lines in enumerate(frames[a:b]):
        out += [str(i + 1), *lines]
    return "\n".join(out) + "\n"


def bvh_window(text: str, start_s: float, duration_s: float) -> str:
    """The BVH's frames from start_s for duration_s, with its hierarchy and a new frame count."""
    lines = text.splitlines()
    at = next(i for i, line in enumerate(lines) if line.strip().lower().startswith("frame time"))
    dt = float(lines[at].split(":")[1])
    frames = [line for line in lines[at + 1:] if line.strip()]
    a, b = int(round(start_s / dt)), int(round((start_s + duration_s) / dt))
    head = [line for line in lines[:at] if not line.strip().lower().startswith("frames")]
    return "\n".join([*head, f"Frames: {len(frames[a:b])}", lines[at], *frames[a:b]]) + "\n"


def phenotypes(name: str) -> dict[str, float]:
    values = BODIES[name] if name in BODIES else np.array([float(x) for x in name.split(",")])
    if len(values) != len(PHENOTYPES):
        raise SystemExit(f"body {name!r}: a name of {sorted(BODIES)} or {len(PHENOTYPES)} numbers")
    # a float32 value as its shortest decimal (0.77 stays 0.77: its float64 widening, 0.76999998..., is
    # below the service's adult age bound)
    return dict(zip(PHENOTYPES, (float(str(np.float32(v))) for v in values)))


def garment_row(vertices: np.ndarray, body: np.ndarray, body_faces: np.ndarray, asset, method: str) -> dict:
    faces = asset.faces
    edges = mesh_edges(faces)
    rest = np.linalg.norm(asset.vertices[edges[:, 1]] - asset.vertices[edges[:, 0]], axis=-1)
    stretch = np.linalg.norm(vertices[:, edges[:, 1]] - vertices[:, edges[:, 0]], axis=-1) / np.maximum(rest, 1e-9)
    step = np.linalg.norm(np.diff(vertices, axis=0), axis=-1) if len(vertices) > 1 else np.zeros((1, 1))
    return {"method": method, "finite": bool(np.isfinite(vertices).all()),
            "inside_pct": round(100 * float(inside_mask(vertices, body, body_faces).mean()), 4),
            "stretch_max": round(float(stretch.max()), 2), "edges_over_2x_pct": round(100 * float((stretch > 2).mean()), 3),
            "step_max_cm": round(100 * float(step.max()), 2), "step_p999_cm": round(100 * float(np.percentile(step, 99.9)), 2)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mocap-dir", type=Path, help="CMU ASF/AMC folders: <dir>/<subject>/<subject>.asf, <clip>.amc")
    ap.add_argument("--window", action="append", default=[], help="CLIP:START_S:DURATION_S of --mocap-dir (repeatable)")
    ap.add_argument("--bvh", action="append", default=[], help="FILE.bvh:START_S:DURATION_S (repeatable)")
    ap.add_argument("--body", action="append", help="a BODIES name or six phenotypes (repeatable; default heavy)")
    ap.add_argument("--garments", action="append", help="garment ids, innermost first, comma-separated (repeatable; default tshirt,jacket)")
    ap.add_argument("--lbs", action="store_true", help="also the plain skinning baseline of each drape")
    args = ap.parse_args(argv)
    if args.window and args.mocap_dir is None:
        ap.error("--window needs --mocap-dir")
    if not args.window and not args.bvh:
        ap.error("give at least one --window or --bvh")
    runtime = Runtime.load(Settings())
    variants = [("default", {})] + ([("lbs", {"fit": "retarget", "dynamics": "none", "collisions": "off"})] if args.lbs else [])
    motions = []
    for window in args.window:
        clip, start, duration = window.split(":")
        subject = clip.split("_")[0]
        asf = (args.mocap_dir / subject / f"{subject}.asf").read_text()
        amc = amc_window((args.mocap_dir / subject / f"{clip}.amc").read_text(), float(start), float(duration))
        motions.append((window, {"type": "asf_amc", "asf": asf, "amc": amc}))
    for window in args.bvh:
        path, start, duration = window.rsplit(":", 2)
        motions.append((f"{Path(path).stem}:{start}:{duration}", {"type": "bvh", "bvh": bvh_window(Path(path).read_text(), float(start), float(duration))}))
    for window, motion in motions:
        for body_name in args.body or ["heavy"]:
            for outfit in args.garments or ["tshirt,jacket"]:
                ids = outfit.split(",")
                posed_body = None
                for variant, options in variants:
                    request = DrapeRequest.model_validate({"body": {"phenotypes": phenotypes(body_name)},
                                                           "motion": motion,
                                                           "garments": [{"id": g} for g in ids], "format": "npz",
                                                           "options": {"fps": 30, **options}})
                    row = {"window": window, "body": body_name, "outfit": outfit, "variant": variant}
                    t0 = time.perf_counter()
                    try:
                        result = runtime.drape_batch([runtime.prepare(request)])[0]
                    except Exception as exc:  # noqa: BLE001 - a failure is what the sweep looks for
                        print(json.dumps({**row, "error": repr(exc)}), flush=True)
                        continue
                    posed_body = result.body_vertices if posed_body is None else posed_body  # the baseline has none
                    if posed_body is None:
                        print(json.dumps({**row, "error": "no posed body (the default drape failed)"}), flush=True)
                        continue
                    row["frames"] = len(posed_body)
                    row["ms_per_frame"] = round((time.perf_counter() - t0) * 1e3 / len(posed_body), 1)
                    for g in result.garments:
                        row[g.asset.id] = garment_row(g.vertices, posed_body, runtime.body.faces, g.asset, f"{g.method.fit}/{g.method.dynamics}")
                    if variant == "default" and len(result.garments) > 1:
                        V = [g.vertices for g in result.garments]
                        for i in range(len(V) - 1):
                            outer = result.garments[i + 1].asset.faces
                            row[f"beyond_{i}{i + 1}_pct"] = round(layer_beyond_pct(V[i], result.anchors[i], posed_body, V[i + 1], outer), 3)
                            row[f"pairs_{i}{i + 1}_per_frame"] = round(float(layer_intersections(V[i], result.garments[i].asset.faces, V[i + 1], outer).mean()), 1)
                    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
