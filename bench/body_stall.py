"""How long a large request body stalls the API's event loop: /healthz latency while clients
post large ``poses`` bodies to /v1/drape.

    python -m bench.body_stall --url http://127.0.0.1:8000 --frames 8000 --clients 3 --rounds 3

Each client posts a ``frames``-frame pose sequence (~0.85 KB per frame; 8000 frames ~6.8 MB,
refused after validation for its frame count, so only reading, validating and keying the body
is measured), while a probe GETs /healthz every 10 ms; prints the probe's p50 / p99 / max
latency during the posts and the posts' own latency.
"""
from __future__ import annotations

import argparse
import json
import statistics
import threading
import time

import httpx
import numpy as np


def poses_body(frames: int) -> bytes:
    rot = np.round(np.random.default_rng(0).normal(size=(frames, 31, 3)) * 0.1, 4).tolist()
    return json.dumps({"motion": {"type": "poses", "fps": 30, "rotations": rot, "translation": [[0, 0, 0]] * frames},
                       "garments": [{"id": "tshirt"}], "format": "npz"}).encode()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000")
    parser.add_argument("--frames", type=int, default=8000)
    parser.add_argument("--clients", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    body = poses_body(args.frames)
    probes, posts, stop = [], [], threading.Event()

    def probe():
        with httpx.Client(timeout=60) as c:
            while not stop.is_set():
                t0 = time.perf_counter()
                c.get(f"{args.url}/healthz")
                probes.append(time.perf_counter() - t0)
                time.sleep(0.01)

    def client():
        with httpx.Client(timeout=120) as c:
            for _ in range(args.rounds):
                t0 = time.perf_counter()
                r = c.post(f"{args.url}/v1/drape", content=body, headers={"content-type": "application/json"})
                posts.append((time.perf_counter() - t0, r.status_code))

    p = threading.Thread(target=probe)
    p.start()
    time.sleep(0.5)
    threads = [threading.Thread(target=client) for _ in range(args.clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stop.set()
    p.join()
    q = sorted(probes)
    print(f"body {len(body) / 1e6:.1f} MB x {args.clients} clients x {args.rounds}: /healthz p50 {statistics.median(q) * 1e3:.0f} ms, "
          f"p99 {q[int(0.99 * (len(q) - 1))] * 1e3:.0f} ms, max {q[-1] * 1e3:.0f} ms ({len(q)} probes); posts p50 "
          f"{statistics.median(t for t, _ in posts):.2f} s, statuses {sorted({s for _, s in posts})}")


if __name__ == "__main__":
    main()
