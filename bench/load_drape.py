"""Load test of POST /v1/drape: throughput and latency at several concurrencies, batching on
and off, and behaviour under 2x overload. Reproducible: starts its own server on 127.0.0.1,
fixed request mix (seeded), bounded duration; traffic only to 127.0.0.1.

Run: ``python bench/load_drape.py`` (defaults: concurrency 1 4 16 64, 12 s per level, batching
on (max_batch 8) and off (max_batch 1), then 20 s at 2x the measured capacity). Prints Markdown
tables (copied into docs/benchmarks.md, section "Serving", with the machine description).

Requests: 30 frames (``--frames``; 1 s of the 'dance' clip at 30 fps from a random start), one garment (tshirt;
``--garments``: an outfit, innermost first; every garment's frames count),
the default neutral body, npz, include_body false, guard on; every request is distinct (the
cache is off too: TRYON_CACHE_MAX_BYTES=0), all share body, garment and options, so the batcher
may merge them. Throughput is garment-frames per second of successful responses.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import random
import socket
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
FRAMES = 30
GARMENTS = ["tshirt"]


# extra request options for every request (--options)
EXTRA_OPTIONS: dict = {}


def body(rng: random.Random, frames: int | None = None, guard: bool = True) -> dict:
    frames = FRAMES if frames is None else frames
    duration_s = (frames - 1) / 30.0 if frames > 1 else 0.01  # a clip's duration must be > 0; 0.01 s is one frame
    return {
        "motion": {"type": "clip", "clip": "dance", "start_s": round(rng.uniform(0.0, 9.0), 3), "duration_s": duration_s},
        "garments": [{"id": g} for g in GARMENTS], "format": "npz", "options": {"include_body": False, "guard": guard, **EXTRA_OPTIONS},
    }


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def session_rss_mb(sid: int) -> float:
    """Resident memory of every process in the server's session (API, forkserver, workers)."""
    total = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) == sid:
                total += int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
    return total / 2**20


class Server:
    def __init__(self, env: dict):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        full = {**os.environ, "TRYON_CACHE_MAX_BYTES": "0", "TRYON_JOBS_BACKEND": "off", "TRYON_LOG_LEVEL": "warning", **env}
        self.proc = subprocess.Popen([sys.executable, "-m", "service", "--port", str(self.port), "--log-level", "warning"],
                                     cwd=REPO, env=full, start_new_session=True)
        t0 = time.monotonic()
        while True:
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None or time.monotonic() - t0 > 120:
                raise RuntimeError("server did not start")
            time.sleep(0.2)

    def rss_mb(self) -> float:
        return session_rss_mb(self.proc.pid)

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, 9)


@dataclass
class Run:
    latencies_ok: list[float] = field(default_factory=list)
    latencies_503: list[float] = field(default_factory=list)
    errors: dict[str, int] = field(default_factory=dict)
    timeouts: int = 0
    wall_s: float = 0.0
    rss_peak_mb: float = 0.0
    batch_mean: float = 0.0

    def row(self, label: str) -> str:
        ok = sorted(self.latencies_ok)
        q = (lambda p: ok[min(len(ok) - 1, int(p * len(ok)))] * 1e3 if ok else float("nan"))  # noqa: E731
        gfs = len(ok) * FRAMES * len(GARMENTS) / self.wall_s
        err = sum(self.errors.values()) + self.timeouts
        return (f"| {label} | {len(ok)} | {gfs:.0f} | {q(0.5):.0f} | {q(0.95):.0f} | {q(0.99):.0f} | {len(self.latencies_503)} | {err} | "
                f"{self.batch_mean:.1f} | {self.rss_peak_mb:.0f} |")


HEADER = ["| run | ok | garment-frames/s | p50 ms | p95 ms | p99 ms | 503 | errors+timeouts | mean batch | peak RSS MB |",
          "|---|---|---|---|---|---|---|---|---|---|"]


async def _one(client: httpx.AsyncClient, payload: dict, run: Run) -> None:
    t0 = time.perf_counter()
    try:
        r = await client.post("/v1/drape", json=payload)
    except httpx.TimeoutException:
        run.timeouts += 1
        return
    except httpx.HTTPError as exc:
        run.errors[type(exc).__name__] = run.errors.get(type(exc).__name__, 0) + 1
        return
    dt = time.perf_counter() - t0
    if r.status_code == 200:
        run.latencies_ok.append(dt)
    elif r.status_code == 503:
        run.latencies_503.append(dt)
    else:
        run.errors[str(r.status_code)] = run.errors.get(str(r.status_code), 0) + 1


def _batch_stats(url: str) -> tuple[float, float]:
    text = httpx.get(url + "/metrics", timeout=5).text
    vals = {line.split()[0]: float(line.split()[1]) for line in text.splitlines() if line.startswith("tryon_batch_size_")}
    return vals.get("tryon_batch_size_sum", 0.0), vals.get("tryon_batch_size_count", 0.0)


async def _monitor(server: Server, run: Run, stop: asyncio.Event) -> None:
    while not stop.is_set():
        run.rss_peak_mb = max(run.rss_peak_mb, server.rss_mb())
        await asyncio.sleep(0.5)


async def closed_loop(server: Server, concurrency: int, duration_s: float, seed: int, timeout_s: float) -> Run:
    """``concurrency`` clients, each sending its next request when the last one is answered."""
    rng = random.Random(seed)
    run = Run()
    s0, c0 = _batch_stats(server.url)
    stop = asyncio.Event()
    limits = httpx.Limits(max_connections=concurrency + 8, max_keepalive_connections=concurrency + 8)
    async with httpx.AsyncClient(base_url=server.url, timeout=timeout_s, limits=limits) as client:
        deadline = time.perf_counter() + duration_s

        async def user():
            while time.perf_counter() < deadline:
                await _one(client, body(rng), run)
                if run.latencies_503 and run.latencies_503[-1] < 0.05:
                    await asyncio.sleep(0.05)  # a refused client backs off a little before retrying

        mon = asyncio.create_task(_monitor(server, run, stop))
        t0 = time.perf_counter()
        await asyncio.gather(*(user() for _ in range(concurrency)))
        run.wall_s = time.perf_counter() - t0
        stop.set()
        await mon
    s1, c1 = _batch_stats(server.url)
    run.batch_mean = (s1 - s0) / max(c1 - c0, 1)
    return run


async def open_loop(server: Server, rate_per_s: float, duration_s: float, seed: int, timeout_s: float) -> Run:
    """Poisson arrivals at ``rate_per_s`` whatever the server does (an overload test)."""
    rng = random.Random(seed)
    run = Run()
    s0, c0 = _batch_stats(server.url)
    stop = asyncio.Event()
    async with httpx.AsyncClient(base_url=server.url, timeout=timeout_s, limits=httpx.Limits(max_connections=512)) as client:
        mon = asyncio.create_task(_monitor(server, run, stop))
        tasks = []
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < duration_s:
            tasks.append(asyncio.create_task(_one(client, body(rng), run)))
            await asyncio.sleep(rng.expovariate(rate_per_s))
        await asyncio.gather(*tasks)
        run.wall_s = time.perf_counter() - t0
        stop.set()
        await mon
    s1, c1 = _batch_stats(server.url)
    run.batch_mean = (s1 - s0) / max(c1 - c0, 1)
    return run


def machine() -> str:
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name")), "?")
    mem = int(next(line.split()[1] for line in Path("/proc/meminfo").read_text().splitlines() if line.startswith("MemTotal"))) / 2**20
    return f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB RAM, {platform.system()} {platform.release()}, Python {platform.python_version()}"


def main() -> None:
    global FRAMES, GARMENTS
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--levels", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--duration", type=float, default=12.0, help="seconds per concurrency level")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-batch", type=int, default=8)
    ap.add_argument("--max-wait-ms", type=float, default=5.0)
    ap.add_argument("--modes", nargs="+", default=["batch", "nobatch"], choices=["batch", "nobatch", "thread"])
    ap.add_argument("--overload-seconds", type=float, default=20.0, help="0: skip the 2x overload run")
    ap.add_argument("--timeout", type=float, default=60.0, help="client timeout, seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=30, help="frames per request (1: the single-frame latency)")
    ap.add_argument("--garments", default="tshirt", help="garment ids of every request, innermost first, comma-separated")
    ap.add_argument("--options", type=json.loads, default={}, help='extra request options, JSON (e.g. \'{"guard_check": false}\')')
    args = ap.parse_args()
    EXTRA_OPTIONS.update(args.options)
    FRAMES = args.frames
    GARMENTS = args.garments.split(",")

    print(f"machine: {machine()}\n")
    print("\n".join(HEADER))
    capacity_rps = 0.0
    for mode in args.modes:
        env = {"TRYON_WORKERS": str(args.workers), "TRYON_MAX_WAIT_MS": str(args.max_wait_ms),
               "TRYON_MAX_BATCH": str(1 if mode == "nobatch" else args.max_batch),
               "TRYON_WORKER_MODE": "thread" if mode == "thread" else "process"}
        server = Server(env)
        try:
            asyncio.run(closed_loop(server, 2, 3.0, args.seed + 99, args.timeout))  # warm-up
            for c in args.levels:
                run = asyncio.run(closed_loop(server, c, args.duration, args.seed + c, args.timeout))
                label = {"batch": f"batching on (max_batch {args.max_batch})", "nobatch": "batching off", "thread": f"threads, batching on"}[mode]
                print(run.row(f"{label}, c={c}"), flush=True)
                if mode == "batch":
                    capacity_rps = max(capacity_rps, len(run.latencies_ok) / run.wall_s)
        finally:
            server.stop()
    if args.overload_seconds > 0 and capacity_rps > 0:
        server = Server({"TRYON_WORKERS": str(args.workers), "TRYON_MAX_BATCH": str(args.max_batch), "TRYON_MAX_WAIT_MS": str(args.max_wait_ms)})
        try:
            asyncio.run(closed_loop(server, 2, 3.0, args.seed + 99, args.timeout))
            rss0 = server.rss_mb()
            run = asyncio.run(open_loop(server, 2 * capacity_rps, args.overload_seconds, args.seed + 1000, args.timeout))
            print(run.row(f"2x overload, open loop {2 * capacity_rps:.1f} req/s for {args.overload_seconds:g} s"))
            r503 = sorted(run.latencies_503)
            if r503:
                print(f"\n503 answers: {len(r503)}, p50 {statistics.median(r503) * 1e3:.1f} ms, max {r503[-1] * 1e3:.1f} ms; "
                      f"client timeouts {run.timeouts}; RSS before {rss0:.0f} MB, peak {run.rss_peak_mb:.0f} MB")
        finally:
            server.stop()


if __name__ == "__main__":
    main()
