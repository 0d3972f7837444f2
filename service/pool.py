"""The inference worker pool: a bounded queue, a batching scheduler and crash-isolated workers.

    request -> queue (bounded: 503 + Retry-After when full; each item has a deadline)
            -> scheduler: when a worker is free, take the oldest item plus up to max_batch - 1
               queued items with the same merge key (service/batching.py), waiting at most
               max_wait_ms for more while no other worker is idle -> worker -> one outcome
               per item

Workers are processes by default (``worker_mode='process'``): a worker that dies (segfault,
OOM kill) or hangs is detected, killed and replaced; each of its requests is retried once, alone,
and answered 500 problem+json if that fails too. ``worker_mode='thread'`` runs the same work on
threads of the API process (no crash isolation; the numpy stages hold the GIL part of the time).
"""
from __future__ import annotations

import asyncio
import itertools
import logging
import math
import multiprocessing
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from inference.defaults import DefaultMethods, default_methods
from service.batching import merge_key
from service.config import Settings
from service.errors import ProblemDetail, ProblemException
from service.metrics import Metrics
from service.runtime import MODEL_VERSIONS, DrapeOutput, Runtime
from service.schemas import DrapeRequest

log = logging.getLogger(__name__)

STAGE_MODELS = {"shape": "body", "arms": "arms", "pose": "body", "body_skin": "body", "fit": "fit", "dynamics": "dynamics", "skin": "body", "strain": "dynamics", "guard": "guard", "repair": "repair", "layers": "layers"}


class WorkerCrashed(Exception):
    """The worker died (or hung and was killed) while holding a batch."""


class ProcessWorker:
    """One worker process and the pipe to it (calls are blocking: made from a thread)."""

    def __init__(self, index: int, settings: Settings):
        self.index, self.settings = index, settings
        self.proc = None
        self.conn = None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def start(self) -> None:
        from service.worker import serve_pipe

        ctx = _context(self.settings.worker_blas_threads)
        parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=serve_pipe, args=(child, self.settings, os.getpid()), name=f"tryon-worker-{self.index}", daemon=True)
        self.proc.start()
        child.close()
        self.conn = parent
        deadline = time.monotonic() + self.settings.worker_start_timeout_s
        while not parent.poll(0.1):
            if not self.proc.is_alive() or time.monotonic() > deadline:
                self.kill()
                raise WorkerCrashed(f"worker {self.index} did not start")
        try:
            parent.recv()  # ("ready", pid)
        except (EOFError, OSError) as exc:
            raise WorkerCrashed(f"worker {self.index} did not start") from exc

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    def call(self, message: tuple, on_progress: Callable[[int, int], bool] | None = None) -> Any:
        t0 = time.monotonic()
        try:
            self.conn.send(message)
            while True:
                if not self.conn.poll(0.2):
                    if not self.proc.is_alive():
                        raise WorkerCrashed(f"worker {self.index} (pid {self.pid}) died, exit code {self.proc.exitcode}")
                    if time.monotonic() - t0 > self.settings.worker_hang_s:
                        self.kill()
                        raise WorkerCrashed(f"worker {self.index} hung for {self.settings.worker_hang_s:.0f} s and was killed")
                    continue
                reply = self.conn.recv()
                if reply[0] == "progress":
                    self.conn.send(bool(on_progress(reply[1], reply[2])) if on_progress else False)
                    continue
                return reply[1]
        except (EOFError, OSError, BrokenPipeError) as exc:
            raise WorkerCrashed(f"worker {self.index} (pid {self.pid}) died: {exc!r}") from exc

    def kill(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.kill()
        if self.proc is not None:
            self.proc.join(5)

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.proc is None:
            return
        try:
            self.conn.send(None)
        except (OSError, BrokenPipeError):
            pass
        self.proc.join(timeout_s)
        self.kill()


def _context(blas_threads: int = 1):
    """forkserver: workers fork from a clean server process that has imported the pipeline once
    (no threads or event loop of the API inherited, unlike fork; ~10x faster starts than spawn).

    The server process, and so every worker, gets ``blas_threads`` BLAS/OpenMP threads (the
    environment it is started with; the first call decides). With OpenBLAS's default of one
    thread per core, each worker's matrix products woke threads that then competed with the
    single-threaded stages on the same cores: the 300-frame T-shirt took 5.0 s over HTTP instead
    of 4.3 s, with the arms and the guard 10-40 % slower (docs/benchmarks.md)."""
    global _CONTEXT
    if _CONTEXT is None:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(blas_threads)
        _CONTEXT = multiprocessing.get_context("forkserver")
        _CONTEXT.set_forkserver_preload(["service.worker", "service.runtime"])
    return _CONTEXT


_CONTEXT = None


class ThreadWorker:
    """The same calls, run on the calling thread against a shared in-process runtime."""

    def __init__(self, index: int, runtime: Runtime):
        self.index, self.runtime = index, runtime
        self.pid = None

    def start(self) -> None:
        pass

    def alive(self) -> bool:
        return True

    def call(self, message: tuple, on_progress: Callable[[int, int], bool] | None = None) -> Any:
        from service.errors import problem_from_exception
        from service.worker import execute_job

        if message[0] == "drape":
            return self.runtime.run_batch(message[1])
        if message[0] == "body":
            return self.runtime.bodies.run(message[1], message[2])
        try:
            return execute_job(self.runtime, message[1], message[2], on_progress)
        except Exception as exc:  # noqa: BLE001
            return problem_from_exception(exc)

    def kill(self) -> None:
        pass

    def stop(self, timeout_s: float = 5.0) -> None:
        pass


@dataclass
class _Item:
    kind: str  # "drape" | "job" | "body"
    payload: tuple
    future: asyncio.Future
    deadline: float  # loop time
    key: tuple | None = None
    frames_hint: int = 0
    attempts: int = 0
    enqueued: float = 0.0
    on_progress: Callable[[int, int], bool] | None = None
    seq: int = field(default_factory=itertools.count().__next__)


class WorkerPool:
    def __init__(self, settings: Settings, runtime: Runtime | None = None, metrics: Metrics | None = None):
        self.settings = settings
        self.runtime = runtime
        self.metrics = metrics or Metrics()
        self.workers: list[ProcessWorker | ThreadWorker] = []
        self._pending: deque[_Item] = deque()
        self._idle: asyncio.Queue | None = None
        self._wakeup: asyncio.Event | None = None
        self._scheduler: asyncio.Task | None = None
        self._running: set[asyncio.Task] = set()
        self._busy = 0
        self._busy_drapes = 0
        self._accepting = False
        self._batch_s = 1.0  # moving average of a batch's time, for Retry-After
        self._item_s = 0.0  # moving average of a drape's share of its batch's time, for admission
        self._gf_s = 0.0  # moving average of the seconds per garment-frame of drape batches, for admit_cost
        self._busy_items = 0
        self._lock = threading.Lock()
        self.defaults: DefaultMethods | None = None  # each garment's default method, for the merge key (set by start)

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        s = self.settings
        self._idle, self._wakeup = asyncio.Queue(), asyncio.Event()
        if s.worker_mode == "process":
            self.workers = [ProcessWorker(i, s) for i in range(s.workers)]
            await asyncio.gather(*(asyncio.to_thread(w.start) for w in self.workers))
        else:
            if self.runtime is None:
                self.runtime = await asyncio.to_thread(Runtime.load, s)
            self.workers = [ThreadWorker(i, self.runtime) for i in range(s.workers)]
        # the runtime's table (process workers each load the same file at their start)
        self.defaults = self.runtime.defaults if self.runtime is not None else default_methods(s.assets_dir)
        for w in self.workers:
            self._idle.put_nowait(w)
        self.metrics.workers_alive.set(len(self.workers))
        self._accepting = True
        self._scheduler = asyncio.create_task(self._schedule(), name="tryon-scheduler")
        log.info("worker pool: %d %s workers, max_batch=%d, max_wait_ms=%g, max_queue=%d",
                 s.workers, s.worker_mode, s.max_batch, s.max_wait_ms, s.max_queue)

    async def close(self) -> None:
        """Graceful shutdown: refuse new work, let queued and running work finish (up to
        shutdown_drain_s), then stop the workers; what is left is answered 503."""
        self._accepting = False
        deadline = time.monotonic() + self.settings.shutdown_drain_s
        # jobs are not waited for: the job runner re-queues them, they restart on the next start
        while (any(it.kind == "drape" for it in self._pending) or self._busy_drapes) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        if self._scheduler is not None:
            self._scheduler.cancel()
        while self._pending:
            item = self._pending.popleft()
            _fail(item, ProblemException(503, "Shutting down", "the service is restarting; retry", headers={"Retry-After": "5"}))
        for task in list(self._running):
            task.cancel()
        await asyncio.gather(*(asyncio.to_thread(w.stop, 0.5) for w in self.workers))
        self.metrics.workers_alive.set(0)

    @property
    def ready(self) -> bool:
        return self._accepting and any(w.alive() for w in self.workers)

    def worker_health(self) -> list[dict]:
        return [{"index": w.index, "pid": w.pid, "alive": w.alive()} for w in self.workers]

    @property
    def queue_depth(self) -> int:
        return len(self._pending)

    # ------------------------------------------------------------------ submit
    def expected_wait_s(self) -> float:
        """Queueing time of a new request: the queued and running requests ahead of it, at the
        measured seconds per request (a moving average; batching lowers it), over the workers."""
        ahead = len(self._pending) + self._busy_items - (len(self.workers) - self._busy)
        return max(ahead, 0) * self._item_s / max(len(self.workers), 1)

    def _retry_after_s(self) -> int:
        waves = (len(self._pending) + self._busy) / max(len(self.workers) * self.settings.max_batch, 1)
        return max(1, math.ceil(waves * self._batch_s))

    def admit(self) -> None:
        """503 (with Retry-After) when a new drape would not be taken: shutting down, the queue
        full, or the expected wait past ``max_queue_wait_s``. Cheap: the route calls it before
        reading the request body."""
        if not self._accepting:
            self.metrics.rejected.labels("shutting_down").inc()
            raise ProblemException(503, "Shutting down", "the service is not accepting work; retry", headers={"Retry-After": "5"})
        if len(self._pending) - (len(self.workers) - self._busy) >= self.settings.max_queue:  # waiting beyond the free workers
            self.metrics.rejected.labels("queue_full").inc()
            raise ProblemException(503, "Busy", f"the queue is full ({self.settings.max_queue} requests); retry later",
                                   headers={"Retry-After": str(self._retry_after_s())})
        expected_wait_s = self.expected_wait_s()
        if expected_wait_s > self.settings.max_queue_wait_s:
            self.metrics.rejected.labels("queue_wait").inc()
            raise ProblemException(503, "Busy", f"the expected wait ({expected_wait_s:.1f} s) exceeds {self.settings.max_queue_wait_s:g} s; retry later",
                                   headers={"Retry-After": str(self._retry_after_s())})

    def admit_cost(self, frames: int | None, garments: int) -> None:
        """422 when the drape is estimated to outlast the request deadline: the expected wait plus
        frames x garments x the measured seconds per garment-frame (audit D10). Such a request
        belongs on POST /v1/jobs. No estimate before the first measured batch, or where the
        frame count is not known from the request (a BVH without a readable MOTION header)."""
        if frames is None or self._gf_s == 0:
            return
        work_s = frames * garments * self._gf_s
        estimate_s = self.expected_wait_s() + work_s
        if estimate_s > self.settings.request_timeout_s:
            self.metrics.rejected.labels("too_long").inc()
            raise ProblemException(422, "Too long for a synchronous drape",
                                   f"{frames} frames x {garments} garment(s) at the measured {self._gf_s * 1e3:.0f} ms per garment-frame "
                                   f"take about {work_s:.0f} s (plus {estimate_s - work_s:.0f} s of queue), past the {self.settings.request_timeout_s:g} s "
                                   "deadline: use POST /v1/jobs, or shorten the motion, lower options.fps or drape fewer garments",
                                   [{"pointer": "/motion", "detail": "too many frames for a synchronous drape; use POST /v1/jobs"}])

    async def drape(self, request: DrapeRequest, timeout_s: float | None = None) -> DrapeOutput:
        """Run a drape through the queue; 503 when the queue is full, 504 past the deadline."""
        self.admit()
        loop = asyncio.get_running_loop()
        timeout_s = timeout_s or self.settings.request_timeout_s
        item = _Item("drape", (request,), loop.create_future(), loop.time() + timeout_s, key=merge_key(request, self.defaults), enqueued=loop.time())
        self._enqueue(item)
        try:
            return await asyncio.wait_for(asyncio.shield(item.future), timeout_s)
        except asyncio.TimeoutError:
            self.metrics.rejected.labels("deadline").inc()
            raise ProblemException(504, "Deadline exceeded", f"the drape did not finish within {timeout_s:g} s") from None
        finally:
            if not item.future.done():
                item.future.cancel()  # the scheduler drops it, or discards its result

    async def body(self, operation: str, request):
        """A body fit or measurement ('fit' | 'measure', ``service.bodies``) on a worker: short
        interactive work, so it goes to the front of the queue; 503 when the queue is full."""
        self.admit()
        loop = asyncio.get_running_loop()
        timeout_s = self.settings.request_timeout_s
        item = _Item("body", (operation, request), loop.create_future(), loop.time() + timeout_s, enqueued=loop.time())
        self._enqueue(item, front=True)
        try:
            outcome = await asyncio.wait_for(asyncio.shield(item.future), timeout_s)
        except asyncio.TimeoutError:
            raise ProblemException(504, "Deadline exceeded", f"the body did not finish within {timeout_s:g} s") from None
        finally:
            if not item.future.done():
                item.future.cancel()
        if isinstance(outcome, ProblemDetail):
            raise outcome.exception()
        return outcome

    async def run_job(self, request: DrapeRequest, result_path: Path, on_progress: Callable[[int, int], bool] | None = None):
        """Run a job on a worker (not merged with other work): a JobOutcome, None (cancelled)
        or a ProblemDetail. Raises WorkerCrashed when the job crashed its worker twice."""
        loop = asyncio.get_running_loop()
        item = _Item("job", (request, str(result_path)), loop.create_future(), loop.time() + self.settings.job_timeout_s,
                     enqueued=loop.time(), on_progress=on_progress)
        self._enqueue(item)
        return await item.future

    def _enqueue(self, item: _Item, front: bool = False) -> None:
        (self._pending.appendleft if front else self._pending.append)(item)
        self.metrics.queue_depth.set(len(self._pending))
        self._wakeup.set()

    # ------------------------------------------------------------------ schedule
    async def _next_item(self) -> _Item:
        loop = asyncio.get_running_loop()
        while True:
            while not self._pending:
                self._wakeup.clear()
                await self._wakeup.wait()
            item = self._pending.popleft()
            if item.future.done():
                continue  # the client gave up
            if loop.time() > item.deadline:
                _fail(item, ProblemException(504, "Deadline exceeded", "the request waited past its deadline"))
                continue
            return item

    def _take_compatible(self, batch: list[_Item]) -> None:
        key = batch[0].key
        kept: deque[_Item] = deque()
        while self._pending and len(batch) < self.settings.max_batch:
            item = self._pending.popleft()
            if item.future.done():
                continue
            (batch.append if item.kind == "drape" and item.key == key and item.attempts == 0 else kept.append)(item)
        kept.extend(self._pending)
        self._pending = kept

    async def _schedule(self) -> None:
        loop = asyncio.get_running_loop()
        s = self.settings
        while True:
            worker = await self._idle.get()
            first = await self._next_item()
            batch = [first]
            # wait for requests to merge only while no other worker is idle: one that arrives
            # meanwhile would otherwise start at once on an idle worker (at low load the wait is
            # pure latency)
            if first.kind == "drape" and first.key is not None and first.attempts == 0 and s.max_batch > 1 and self._idle.empty():
                wait_until = first.enqueued + s.max_wait_ms / 1e3
                while True:
                    self._take_compatible(batch)
                    remaining = wait_until - loop.time()
                    if len(batch) >= s.max_batch or remaining <= 0:
                        break
                    self._wakeup.clear()
                    try:
                        await asyncio.wait_for(self._wakeup.wait(), remaining)
                    except asyncio.TimeoutError:
                        pass
            self.metrics.queue_depth.set(len(self._pending))
            task = asyncio.create_task(self._dispatch(worker, batch))
            self._running.add(task)
            task.add_done_callback(self._running.discard)

    async def _dispatch(self, worker, batch: list[_Item]) -> None:
        drapes = int(batch[0].kind == "drape")
        self._busy += 1
        self._busy_drapes += drapes
        self.metrics.workers_busy.set(self._busy)
        t0 = time.perf_counter()
        try:
            if batch[0].kind == "drape":
                self.metrics.batch_size.observe(len(batch))
                self._busy_items += len(batch)
                message = ("drape", [it.payload[0] for it in batch])
                try:
                    outcomes = await asyncio.to_thread(worker.call, message)
                finally:
                    self._busy_items -= len(batch)
                for item, outcome in zip(batch, outcomes):
                    self._observe(outcome)
                    _settle(item, outcome)
                elapsed = time.perf_counter() - t0
                item_s = elapsed / len(batch)
                self._item_s = item_s if self._item_s == 0 else 0.8 * self._item_s + 0.2 * item_s
                garment_frames = sum(int(o.headers.get("X-Frames", 0)) * len(it.payload[0].garments)
                                     for it, o in zip(batch, outcomes) if isinstance(o, DrapeOutput))
                if garment_frames:
                    gf_s = elapsed / garment_frames
                    self._gf_s = gf_s if self._gf_s == 0 else 0.8 * self._gf_s + 0.2 * gf_s
            else:
                item = batch[0]
                outcome = await asyncio.to_thread(worker.call, (item.kind,) + item.payload, item.on_progress)
                _settle(item, outcome)
            self._batch_s = 0.8 * self._batch_s + 0.2 * (time.perf_counter() - t0)
        except WorkerCrashed as exc:
            log.error("%s; replacing it", exc)
            self.metrics.worker_restarts.inc()
            for item in batch:
                if item.future.done():
                    continue
                if item.attempts == 0:
                    item.attempts += 1
                    self._enqueue(item, front=True)  # retried once, alone (attempts > 0 is never merged)
                else:
                    _fail(item, WorkerCrashed(str(exc)) if item.kind == "job" else
                          ProblemException(500, "Worker failed", "the inference worker failed twice on this request"))
            worker = await self._replace(worker)
        except Exception as exc:  # noqa: BLE001 - never leave a request hanging
            log.exception("batch failed")
            for item in batch:
                _fail(item, ProblemException(500, "Internal error", "the server failed to process the request"))
        finally:
            self._busy -= 1
            self._busy_drapes -= drapes
            self.metrics.workers_busy.set(self._busy)
            if worker is not None:
                self._idle.put_nowait(worker)

    async def _replace(self, worker):
        """A fresh worker in the dead one's slot (None when it cannot start: the slot is lost,
        /readyz reports it)."""
        await asyncio.to_thread(worker.kill)
        fresh = type(worker)(worker.index, self.settings) if isinstance(worker, ProcessWorker) else worker
        try:
            await asyncio.to_thread(fresh.start)
        except WorkerCrashed:
            log.error("worker %d could not be restarted", worker.index)
            fresh = None
        if fresh is not None:
            self.workers[worker.index] = fresh
        self.metrics.workers_alive.set(sum(w.alive() for w in self.workers))
        return fresh

    def _observe(self, outcome) -> None:
        if isinstance(outcome, DrapeOutput):
            for stage, ms in outcome.timings_ms.items():
                if stage in STAGE_MODELS:  # label: the model(s) this request ran at that stage
                    model = STAGE_MODELS[stage]
                    version = outcome.model_versions.get(model, MODEL_VERSIONS[model])
                    if isinstance(version, dict):  # per garment (fit, dynamics): the distinct versions, sorted
                        version = "+".join(sorted(set(version.values())))
                    self.metrics.inference_ms.labels(stage, version).observe(ms)


def _settle(item: _Item, outcome) -> None:
    if item.future.done():
        return
    if isinstance(outcome, ProblemDetail) and item.kind == "drape":
        item.future.set_exception(outcome.exception())
    else:
        item.future.set_result(outcome)


def _fail(item: _Item, exc: BaseException) -> None:
    if not item.future.done():
        item.future.set_exception(exc)
