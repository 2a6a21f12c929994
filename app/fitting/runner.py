"""Fit jobs: a background runner that claims queued jobs from the store and fits them.

A job is `queued` -> `running` -> `succeeded` | `failed`. The runner claims jobs atomically
(several worker processes may share one store), reports `fit_profile`'s progress, and lands
the profile version and the job's success in one transaction; any exception fails the job
and leaves every stored profile and active pointer as they were.

Each runner is an instance (`host:pid:random`) that owns the jobs it claims and holds a lock
file under `dumps/.runners/` while it lives (app/store/files.py). A job whose owner on this
host no longer holds its lock (its process died, even by `kill -9`) is re-queued at once: at
start-up, and every `poll_s` after; a live sibling process's jobs are never touched. An owner
on another host is taken for dead only after `stale_after` without a heartbeat. Either way a
job interrupted three times fails, and a re-queued job's late result never lands (the store
refuses it). The runner also cleans the dumps directory at start-up and every `clean_every_s`
(`Store.clean_dumps`: partial uploads, and unreferenced dumps older than `dump_grace`).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from datetime import timedelta
from pathlib import Path
from typing import Any

from app.fitting.coco import COCO_RESULTS_KIND, fit_job
from app.fitting.datasets import DATASET_KIND, redact_paths, referenced_dataset
from app.fitting.handoff import ParsedUploads
from app.store import JobLostError, JobRecord, Store
from app.store.files import InstanceLock
from calibrators.fit import FitOptions, fit_profile

log = logging.getLogger("detcal.jobs")

RUNNERS_DIR = ".runners"


def _host(instance: str) -> str:
    """The host part of a runner instance id. Lock files are trusted only between processes
    of one host (a directory shared over the network may not carry `flock` between hosts)."""
    return instance.split(":", 1)[0]


def load_job_dump(store: Store, job: JobRecord, max_bytes: int | None = None) -> Any:
    """The `Dump` a job fits: the stored NPZ, or the stored nuScenes results + GT pair, under
    the same size limit the upload was checked against (None: the library's default)."""
    from calibrators.io import load_dump, load_nuscenes

    path = store.dump_path(job.dump_sha256)
    if job.gt_sha256 is None:
        return load_dump(path, max_bytes=max_bytes)
    return load_nuscenes(path, store.dump_path(job.gt_sha256), max_bytes=max_bytes)


class _Progress:
    """fit_profile's progress callback: throttled writes to the job row, also the heartbeat.

    Raises JobLostError (stopping the fit) once the job is no longer this worker's."""

    def __init__(self, store: Store, job_id: str, worker: str) -> None:
        self.store, self.job_id, self.worker = store, job_id, worker
        self.fraction, self.stage = 0.0, "loading dump"
        self.lost = False
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
        if self.lost:
            raise JobLostError(f"job {self.job_id} was re-queued while it ran here")

    def flush(self) -> None:
        with self._lock:
            self._last = time.monotonic()
            if not self.store.update_job(self.job_id, self.fraction, self.stage, self.worker):
                self.lost = True


class JobRunner:
    """Threads that run queued fit jobs of `store` until `stop()`."""

    def __init__(self, store: Store, workers: int = 1, poll_s: float = 1.0,
                 heartbeat_s: float = 5.0, stale_after: timedelta = timedelta(seconds=30),
                 clean_every_s: float = 600.0, dump_grace: timedelta = timedelta(hours=1),
                 max_dump_bytes: int | None = None, datasets_dir: Path | None = None) -> None:
        self.store, self.workers, self.poll_s = store, workers, poll_s
        self.parsed = ParsedUploads()   # dumps a fit request already parsed, by content hash
        self.max_dump_bytes = max_dump_bytes
        self.datasets_dir = datasets_dir
        self.heartbeat_s, self.stale_after = heartbeat_s, stale_after
        self.clean_every_s, self.dump_grace = clean_every_s, dump_grace
        self.instance = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:12]}"
        self._alive = InstanceLock(store.dumps_dir / RUNNERS_DIR, self.instance)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._running: dict[str, _Progress] = {}
        self._lock = threading.Lock()

    def start(self) -> None:
        """Take this instance's lock, re-queue the jobs of dead processes, clean the dumps
        directory, and start the worker threads and the housekeeping thread."""
        self._alive.acquire()
        self.recover()
        self.clean()
        self._threads = [threading.Thread(target=self._loop, name=f"detcal-fit-{i}", daemon=True)
                         for i in range(self.workers)]
        self._threads.append(threading.Thread(target=self._housekeep,
                                              name="detcal-fit-housekeeping", daemon=True))
        for t in self._threads:
            t.start()

    def notify(self) -> None:
        """Wake a worker: a job was just queued."""
        self._wake.set()

    def stop(self, timeout: float = 5.0) -> None:
        """Ask the threads to stop; a fit still running after `timeout` is re-queued now (for
        the next runner: its result here will not land)."""
        self._stop.set()
        self._wake.set()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        try:
            if self._alive.alive(self.instance):
                self.store.requeue_stale(None, dead_workers={self.instance},
                                         why="its worker was stopped")
        except Exception:  # noqa: BLE001 - stale_after re-queues it later
            log.exception("could not re-queue the fits still running")
        finally:
            self._alive.release()

    def recover(self) -> int:
        """Re-queue (or fail, after three tries) running jobs whose owner on this host is dead,
        and those of any owner silent for `stale_after`; how many."""
        try:
            owners = self.store.running_workers() - {self.instance}
            dead = {w for w in owners if _host(w) == _host(self.instance)
                    and self._alive.alive(w) is False}
            n = self.store.requeue_stale(self.stale_after, dead_workers=dead)
        except Exception:  # noqa: BLE001 - a store hiccup must not kill the runner
            log.exception("could not re-queue interrupted fit jobs")
            return 0
        if n:
            log.warning("re-queued %d interrupted fit job(s)", n)
            self._wake.set()
        return n

    def clean(self) -> None:
        """Remove partial and unreferenced uploads (never a dump a job or profile uses) and the
        lock files of dead runners that own no running job any more."""
        try:
            self._alive.sweep(keep=self.store.running_workers())
            report = self.store.clean_dumps(self.dump_grace)
        except Exception:  # noqa: BLE001 - the next round tries again
            log.exception("could not clean the dumps directory")
            return
        if report.partial or report.dumps:
            log.info("removed %d partial upload(s) and %d unreferenced dump(s), %d bytes",
                     report.partial, report.dumps, report.bytes)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self.store.claim_job(self.instance)
            except Exception:  # noqa: BLE001 - a store hiccup must not kill the runner
                log.exception("could not claim a fit job")
                job = None
            if job is None:
                self._wake.wait(self.poll_s)
                self._wake.clear()
                continue
            self.run(job)

    def _housekeep(self) -> None:
        now = time.monotonic()
        next_beat, next_clean = now + self.heartbeat_s, now + self.clean_every_s
        while not self._stop.wait(self.poll_s):
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + self.heartbeat_s
                self._beat()
            self.recover()
            if now >= next_clean:
                next_clean = now + self.clean_every_s
                self.clean()

    def _beat(self) -> None:
        with self._lock:
            running = list(self._running.values())
        for progress in running:
            try:
                progress.flush()
            except Exception:  # noqa: BLE001
                log.exception("heartbeat failed")

    def _fit(self, job: JobRecord, progress: _Progress) -> Any:
        """The profile of `job`: its stored dump fit in memory, or its Parquet dataset (a
        stored `app.fitting.datasets` reference) fit part by part, or its COCO pair fit as a
        2-D profile (`app.fitting.coco`)."""
        kind = self.store.dump_kind(job.dump_sha256)
        if kind == COCO_RESULTS_KIND:
            pair = self.parsed.take((job.dump_sha256, job.gt_sha256))
            return fit_job(self.store, job, pair, progress, self.max_dump_bytes)
        if kind == DATASET_KIND:
            from calibrators.fit import fit_profile_stream

            path = referenced_dataset(self.datasets_dir, self.store.dump_path(job.dump_sha256))
            progress("fitting", 0.0)
            return fit_profile_stream(path, FitOptions.from_dict(job.options),
                                      progress=progress)
        dump = self.parsed.take((job.dump_sha256, job.gt_sha256))
        if dump is None:
            dump = load_job_dump(self.store, job, self.max_dump_bytes)
        progress("fitting", 0.0)
        return fit_profile(dump, FitOptions.from_dict(job.options),
                           dump_sha256=job.dump_sha256, progress=progress)

    def run(self, job: JobRecord) -> None:
        """Fit one claimed job and record its outcome (never raises)."""
        progress = _Progress(self.store, job.id, self.instance)
        with self._lock:
            self._running[job.id] = progress
        started = time.monotonic()
        try:
            profile = self._fit(job, progress)
            record = self.store.complete_job(job.id, profile.to_json(), self.instance)
            log.info("fit job %s: %s landed in %.1f s%s", job.id, record.ref,
                     time.monotonic() - started, ", active" if record.active else "")
        except JobLostError as exc:
            log.warning("fit job %s: %s", job.id, exc)
        except Exception as exc:  # noqa: BLE001 - every failure is reported on the job
            log.warning("fit job %s failed: %s", job.id, exc)
            why = redact_paths(redact_paths(f"{type(exc).__name__}: {exc}", self.datasets_dir),
                               self.store.dumps_dir, "<dumps>")   # no server path in the job
            try:
                self.store.fail_job(job.id, why, self.instance)
            except Exception:  # noqa: BLE001
                log.exception("could not record the failure of job %s", job.id)
        finally:
            with self._lock:
                self._running.pop(job.id, None)
