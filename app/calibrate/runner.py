"""Calibrate requests run where they cannot stall the server: small bodies in a thread of the
server process (small uncompressed Arrow bodies on the event loop itself), large ones in
calibrate worker processes.

Parsing a large JSON body and building its response are Python work that holds the GIL in
long stretches (pydantic-core validates 20,000 detections in ~0.25 s in one call that never
releases it); in a thread of the server process that stalls the event loop and `/healthz`
with it. A body over `offload_bytes` therefore goes, as bytes, to a pool of `processes`
spawned worker processes, each with its own store connection and profile cache
(`app.calibrate.engine.CalibrateEngine`), and its response comes back as bytes. Small bodies
stay in a thread: the round trip to a process would cost more than the parse.

The pool starts on the first large request (tests and small clients never pay for it). A
worker that dies (killed, out of memory) fails its request with a 503 and the pool is
replaced for the next one. Workers die with the server, even when it is killed with SIGKILL
(`app.calibrate.parent_watch`).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from starlette.concurrency import run_in_threadpool

from app.calibrate.cache import ProfileCache
from app.calibrate.engine import CalibrateCall, CalibrateEngine, CallOutcome
from app.calibrate.parent_watch import die_with_parent
from app.http.content_types import accepts
from app.http.json_body import dumps_json
from app.http.metrics import ServiceMetrics
from app.settings import Settings
from app.store import Store
from calibrators.io.arrow_batch import ARROW_STREAM
from calibrators.io.arrow_safe import plain_stream

log = logging.getLogger("detcal.offload")

_ENGINE: CalibrateEngine | None = None   # the engine of a worker process
#: Uncompressed Arrow bodies up to this size (~1,200 detections) are calibrated on the event
#: loop: reading them is zero-copy and their whole calibration (~0.4 ms at 300 detections,
#: ~1.5 ms here) costs about what handing them to a worker thread and back does; `/healthz`
#: waits at most that long behind one. A compressed body (it may inflate to
#: `MAX_INFLATED_BYTES`), one whose headers do not parse, or one answered in JSON (a 2-D
#: profile's, when `Accept` refuses Arrow: building the document holds the GIL ~10 ms per
#: 1,000 detections) always goes to a thread. A 2-D batch answered in Arrow costs more than a
#: 3-D one (~6 ms at 1,300 detections here) and still runs inline.
INLINE_ARROW_BYTES = 256 * 1024


def _worker_init(settings: Settings, parent_pid: int) -> None:
    """Tie a new worker process's life to the server's (`parent_pid`), then open the store and
    a profile cache in it."""
    global _ENGINE
    die_with_parent(parent_pid)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    _ENGINE = CalibrateEngine(ProfileCache(store), settings.default_profile,
                              settings.max_detections)
    # Everything imported so far lives as long as the process: out of the collector's sight,
    # a full collection (triggered by a request's many short-lived objects) costs ~1 ms, not
    # the ~80 ms of walking every module object.
    gc.freeze()


def _worker_run(call: CalibrateCall) -> CallOutcome:
    assert _ENGINE is not None, "worker not initialised"
    return _ENGINE.run(call)


class CalibrateRunner:
    """Runs `CalibrateCall`s in a thread (small bodies) or a worker process (large ones)."""

    def __init__(self, engine: CalibrateEngine, settings: Settings) -> None:
        self.engine = engine
        self.settings = settings
        self.processes = settings.calibrate_processes
        self.offload_bytes = settings.offload_bytes
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def offloads(self, call: CalibrateCall) -> bool:
        """Whether `call` goes to a worker process."""
        # an Arrow batch is read without copying: nothing there holds the GIL for long
        return (self.processes > 0 and call.kind != "arrow"
                and len(call.body) > self.offload_bytes)

    async def serve(self, call: CalibrateCall, metrics: ServiceMetrics) -> CallOutcome:
        """`run(call)`, counting its calibrated detections per profile in `metrics`."""
        out = await self.run(call)
        if out.profile is not None:
            metrics.detections.labels(out.profile).inc(out.detections)
        return out

    async def run(self, call: CalibrateCall) -> CallOutcome:
        """The outcome of `call`, computed off the event loop."""
        if (call.kind == "arrow" and len(call.body) <= INLINE_ARROW_BYTES
                and accepts(call.accept, ARROW_STREAM) and plain_stream(call.body)):
            return self.engine.run(call)
        if not self.offloads(call):
            return await run_in_threadpool(self.engine.run, call)
        pool = self._ensure_pool()
        try:
            return await asyncio.wrap_future(pool.submit(_worker_run, call))
        except BrokenProcessPool:
            log.error("a calibrate worker process died; replacing the pool")
            self._discard(pool)
            return CallOutcome(503, dumps_json({"detail": "the calibrate worker processing this "
                                                          "request died; retry it"}))

    def _ensure_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=self.processes, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init, initargs=(self.settings, os.getpid()))
            return self._pool

    def _discard(self, pool: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is pool:
                self._pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    def worker_pids(self) -> list[int]:
        """Process ids of the running worker processes (none before the first large body)."""
        with self._lock:
            pool = self._pool
        return [] if pool is None else [p.pid for p in list(pool._processes.values())
                                         if p.pid is not None]

    def close(self) -> None:
        """Stop the worker processes (at shutdown)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
