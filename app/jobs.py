"""Fit jobs: a background runner that claims queued jobs from the store and fits them.

A job is `queued` -> `running` -> `succeeded` | `failed`. The runner claims jobs atomically
(several worker processes may share one store), reports `fit_profile`'s progress, and lands
the profile version and the job's success in one transaction; any exception fails the job
and leaves every stored profile and active pointer as they were. A job whose worker died
(no heartbeat for `stale_after`) is re-queued, up to three attempts.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import timedelta
from typing import Any

from app.store import JobRecord, Store
from calibrators.fit import fit_profile
from calibrators.options import FitOptions

log = logging.getLogger("detcal.jobs")


def load_job_dump(store: Store, job: JobRecord) -> Any:
    """The `Dump` a job fits: the stored NPZ, or the stored nuScenes results + GT pair."""
    from calibrators.io import load_dump, load_nuscenes

    path = store.dump_path(job.dump_sha256)
    if job.gt_sha256 is None:
        return load_dump(path)
    return load_nuscenes(path, store.dump_path(job.gt_sha256))


class _Progress:
    """fit_profile's progress callback: throttled writes to the job row, also the heartbeat."""

    def __init__(self, store: Store, job_id: str) -> None:
        self.store, self.job_id = store, job_id
        self.fraction, self.stage = 0.0, "loading dump"
        self._last = 0.0
        self._lock = threading.Lock()

    def __call__(self, *args: Any, **kwargs: Any) -> None:
        for value in (*args, *kwargs.values()):
            if isinstance(value, int | float) and not isinstance(value, bool):
                self.fraction = float(value)
            elif isinstance(value, str):
                self.stage = value
        now = time.monotonic()
        if now - self._last >= 0.2:
            self.flush()

    def flush(self) -> None:
        with self._lock:
            self._last = time.monotonic()
            self.store.update_job(self.job_id, self.fraction, self.stage)


class JobRunner:
    """Threads that run queued fit jobs of `store` until `stop()`."""

    def __init__(self, store: Store, workers: int = 1, poll_s: float = 1.0,
                 heartbeat_s: float = 5.0, stale_after: timedelta = timedelta(seconds=30)
                 ) -> None:
        self.store, self.workers, self.poll_s = store, workers, poll_s
        self.heartbeat_s, self.stale_after = heartbeat_s, stale_after
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._running: dict[str, _Progress] = {}
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start the worker threads and the heartbeat thread."""
        self._threads = [threading.Thread(target=self._loop, name=f"detcal-fit-{i}", daemon=True)
                         for i in range(self.workers)]
        self._threads.append(threading.Thread(target=self._beat, name="detcal-fit-heartbeat",
                                              daemon=True))
        for t in self._threads:
            t.start()

    def notify(self) -> None:
        """Wake a worker: a job was just queued."""
        self._wake.set()

    def stop(self, timeout: float = 5.0) -> None:
        """Ask the threads to stop; a fit in progress is left to be re-queued by a later run."""
        self._stop.set()
        self._wake.set()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.store.requeue_stale(self.stale_after)
                job = self.store.claim_job()
            except Exception:  # noqa: BLE001 - a store hiccup must not kill the runner
                log.exception("could not claim a fit job")
                job = None
            if job is None:
                self._wake.wait(self.poll_s)
                self._wake.clear()
                continue
            self.run(job)

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            with self._lock:
                running = list(self._running.values())
            for progress in running:
                try:
                    progress.flush()
                except Exception:  # noqa: BLE001
                    log.exception("heartbeat failed")

    def run(self, job: JobRecord) -> None:
        """Fit one claimed job and record its outcome (never raises)."""
        progress = _Progress(self.store, job.id)
        with self._lock:
            self._running[job.id] = progress
        started = time.monotonic()
        try:
            dump = load_job_dump(self.store, job)
            progress("fitting", 0.0)
            profile = fit_profile(dump, FitOptions.from_dict(job.options),
                                  dump_sha256=job.dump_sha256, progress=progress)
            record = self.store.complete_job(job.id, profile.to_json())
            log.info("fit job %s: %s landed in %.1f s", job.id, record.ref,
                     time.monotonic() - started)
        except Exception as exc:  # noqa: BLE001 - every failure is reported on the job
            log.warning("fit job %s failed: %s", job.id, exc)
            try:
                self.store.fail_job(job.id, f"{type(exc).__name__}: {exc}")
            except Exception:  # noqa: BLE001
                log.exception("could not record the failure of job %s", job.id)
        finally:
            with self._lock:
                self._running.pop(job.id, None)
