"""`auto_refit`: when feedback first degrades a champion, queue a fit on that version's
accumulated feedback whose version lands as the alias `challenger`, never activated.

Feedback dumps are kept (content-addressed, like uploads) only while `DETCAL_AUTO_REFIT` is on:
`keep_feedback` stores each request's frames (frame ids made unique per version) and the
version's health row points at them; `queue_refit` concatenates them into one dump and queues
the fit with the options of the job that fit the degraded version (else `FitOptions(holdout=
0.3)`). The audit log records the queued fit with the token id `system:auto-refit`.
"""

from __future__ import annotations

import io
import logging
import uuid
from dataclasses import replace

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.store import AuditEntry, NotFoundError, Store
from calibrators.core.errors import OptionError
from calibrators.data import Dump, concat_frames
from calibrators.fit import FitOptions, check_fit_input
from calibrators.io import load_dump, save_dump

log = logging.getLogger("detcal.refit")

#: The alias an automatic refit lands as.
CHALLENGER = "challenger"
#: Audit id of the writes the service makes on its own.
SYSTEM_TOKEN = "system:auto-refit"


def keep_feedback(store: Store, dump: Dump) -> str:
    """Store `dump` as an NPZ dump (frame ids `<random>-<i>`: unique across requests, so the
    kept dumps of a version concatenate); its sha256."""
    tag = uuid.uuid4().hex[:12]
    ids = np.array([f"{tag}-{i}" for i in range(dump.n_frames)])
    buf = io.BytesIO()
    save_dump(buf, replace(dump, frame_ids=ids))
    buf.seek(0)
    return store.put_dump(buf, "feedback-npz").sha256


def _options(store: Store, loaded: LoadedProfile) -> FitOptions:
    job_id = loaded.record.job_id
    if job_id is not None:
        try:
            return FitOptions.from_dict(store.get_job(job_id).options)
        except (NotFoundError, OptionError):
            pass
    return FitOptions(holdout=0.3)


def queue_refit(store: Store, loaded: LoadedProfile, reason: str,
                max_dump_bytes: int | None = None) -> str | None:
    """Queue the challenger fit of `loaded`'s version on its kept feedback; the job id, or
    None (logged) when the feedback cannot be fit (too little of it, no kept dump)."""
    shas = store.feedback_dumps(loaded.record.id)
    if not shas:
        return None
    dump = concat_frames([load_dump(store.dump_path(s), max_bytes=max_dump_bytes)
                          for s in shas])
    options = _options(store, loaded)
    try:
        check_fit_input(dump, options)
    except (OptionError, ValueError) as exc:
        log.warning("auto_refit of %s skipped: %s", loaded.record.ref, exc)
        return None
    buf = io.BytesIO()
    save_dump(buf, dump)
    buf.seek(0)
    stored = store.put_dump(buf, "npz")
    audit = AuditEntry("fit", loaded.record.name, SYSTEM_TOKEN, {
        "dump_sha256": stored.sha256, "activate": False, "alias": CHALLENGER,
        "reason": reason, "feedback_frames": dump.n_frames})
    job = store.create_job(loaded.record.name, options.to_dict(), stored.sha256, None, False,
                           audit, alias=CHALLENGER)
    log.warning("auto_refit: %s degraded (%s); queued fit job %s -> %s@%s", loaded.record.ref,
                reason, job.id, loaded.record.name, CHALLENGER)
    return job.id
