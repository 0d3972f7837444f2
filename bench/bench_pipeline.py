"""Benchmark: ms per frame of every pipeline stage, and HTTP request latency of /v1/drape.

Run: ``python bench/bench_pipeline.py [--repeats 5] [--mode learned|retarget]`` (starts its own
server on 127.0.0.1). ``--mode``: the pipeline's options for both tables: the learned model (the
default: fit and dynamics 'learned') or the retarget baseline (fit 'retarget', no dynamics).
Prints a Markdown table (copied into docs/benchmarks.md with the machine description).
"""
from __future__ import annotations

import argparse
import os
import platform
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from service.config import Settings  # noqa: E402
from service.runtime import Runtime  # noqa: E402
from service.schemas import DrapeRequest  # noqa: E402


MODES = {"learned": {"fit": "learned", "dynamics": "learned"}, "retarget": {"fit": "retarget", "dynamics": "none"}}
STAGES = ("shape", "arms", "pose", "body_skin", "models", "descriptor", "fit", "dynamics", "skin", "strain", "guard", "repair")


def request(frames: int, fmt: str, garments=("tshirt",), include_body: bool = True, mode: str = "learned") -> dict:
    return {
        # the dance clip is the longest bundled one (312 frames at 30 fps)
        "motion": {"type": "clip", "clip": "dance", "duration_s": max(frames - 1, 0.01) / 30.0},
        "garments": [{"id": g} for g in garments],
        "format": fmt,
        "options": {"fps": 30, "include_body": include_body, **MODES[mode]},
    }


def stage_table(runtime: Runtime, repeats: int, mode: str) -> list[str]:
    from inference.pipeline import DrapeOptions, drape

    rows = ["| garments | frames | " + " | ".join(STAGES) + " | total pipeline | ms/frame |", "|" + "---|" * (len(STAGES) + 4)]
    for garments in (("tshirt",), ("tshirt", "jacket")):
        for frames in (1, 300):
            req = DrapeRequest.model_validate(request(frames, "npz", garments, mode=mode))
            prepared = runtime.prepare(req)
            shape, motion, assets = prepared.shape, prepared.motion, prepared.assets
            runs = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                res = drape(runtime.body, shape, motion, assets, DrapeOptions(**MODES[mode]), neutral=runtime.neutral_shape)
                runs.append(((time.perf_counter() - t0) * 1e3, res.timings_ms))
            total, timings = min(runs, key=lambda r: r[0])
            cells = [f"{timings.get(k, 0.0):.1f}" for k in STAGES]
            rows.append(f"| {'+'.join(garments)} | {frames} | " + " | ".join(cells) + f" | {total:.1f} | {total / frames:.2f} |")
    return rows


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def latency_table(repeats: int, mode: str) -> list[str]:
    port = free_port()
    env = {**os.environ, "TRYON_PORT": str(port), "TRYON_CACHE_MAX_BYTES": "0"}  # measure the work, not the cache
    server = subprocess.Popen([sys.executable, "-m", "service", "--port", str(port), "--log-level", "warning"], cwd=REPO, env=env)
    rows = ["| request | format | p50 ms | max ms | bytes |", "|---|---|---|---|---|"]
    try:
        url = f"http://127.0.0.1:{port}"
        for _ in range(300):
            try:
                if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        with httpx.Client(base_url=url, timeout=120) as client:
            for frames in (1, 300):
                for fmt in ("glb", "npz"):
                    body = request(frames, fmt, mode=mode)
                    client.post("/v1/drape", json=body)  # warm-up
                    times, size = [], 0
                    for _ in range(repeats):
                        t0 = time.perf_counter()
                        r = client.post("/v1/drape", json=body)
                        times.append((time.perf_counter() - t0) * 1e3)
                        r.raise_for_status()
                        size = len(r.content)
                    rows.append(f"| dance, T-shirt + body, {frames} frame(s) | {fmt} | {statistics.median(times):.0f} | {max(times):.0f} | {size:,} |")
    finally:
        server.terminate()
        server.wait(timeout=30)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--mode", choices=sorted(MODES), default="learned")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}")
    runtime = Runtime.load(Settings())
    print("\nPipeline stages (ms, best of %d; in-process, no HTTP; mode %s):\n" % (args.repeats, args.mode))
    print("\n".join(stage_table(runtime, args.repeats, args.mode)))
    print("\nHTTP latency (uvicorn, 1 client, sequential):\n")
    print("\n".join(latency_table(args.repeats, args.mode)))


if __name__ == "__main__":
    main()
