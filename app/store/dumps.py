"""Uploaded dumps: kept content-addressed under `dumps/<sha256>`, recorded in the `dumps` table,
and cleaned up when nothing references them (the `Store`'s upload half).

An upload is written to a private `.upload-*` temporary file and renamed into place while the
writer holds `dumps/.lock` shared; `clean_dumps` holds it exclusively, so every `.upload-*` it
sees then is the remains of a writer that died. A dump that any job (in any state) or any
profile version references is never removed; an unreferenced one only after `grace` since it
was last uploaded, which covers the time between an upload and the job it becomes.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Iterator
from contextlib import AbstractContextManager
from datetime import timedelta
from pathlib import Path
from typing import BinaryIO

from sqlalchemy import delete, func, select, union
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.store.files import DUMP_NAME, LOCK_FILE, UPLOAD_PREFIX, flocked, tighten
from app.store.models import DumpRow, HealthRow, JobRow, ProfileRow, utcnow
from app.store.records import CleanReport, DumpRecord, NotFoundError

_CHUNK = 1 << 20


class DumpFiles:
    """Put, find and clean up uploaded dumps (a base of `Store`, which provides the rest)."""

    dumps_dir: Path
    _session: sessionmaker[Session]

    def _tx(self) -> AbstractContextManager[Session]:
        raise NotImplementedError

    def put_dump(self, source: BinaryIO, kind: str) -> DumpRecord:
        """Copy `source` to `dumps/<sha256>` (atomically, once) and record it (or, for bytes
        already stored, note their use: the clean-up's grace period starts again)."""
        with flocked(self.dumps_dir / LOCK_FILE, exclusive=False):
            sha, size = self._write(source)
            now = utcnow()
            try:
                with self._tx() as s:
                    row = s.get(DumpRow, sha)
                    created = row is None
                    if row is None:
                        s.add(DumpRow(sha256=sha, kind=kind, size=size, created_at=now,
                                      used_at=now))
                    else:
                        row.used_at = now
            except IntegrityError:
                created = False  # the same bytes were recorded concurrently
        return DumpRecord(sha256=sha, kind=kind, size=size, created=created)

    def _write(self, source: BinaryIO) -> tuple[str, int]:
        """`source` into `dumps/<sha256>` through a private temporary file; (sha256, size)."""
        digest = hashlib.sha256()
        size = 0
        fd, tmp = tempfile.mkstemp(dir=self.dumps_dir, prefix=UPLOAD_PREFIX)
        try:
            with os.fdopen(fd, "wb") as out:
                while chunk := source.read(_CHUNK):
                    digest.update(chunk)
                    size += len(chunk)
                    out.write(chunk)
            sha = digest.hexdigest()
            final = self.dumps_dir / sha
            if final.exists():
                os.unlink(tmp)
            else:
                os.replace(tmp, final)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return sha, size

    def dump_kind(self, sha256: str) -> str:
        """The kind a stored upload was recorded with (`npz`, `nuscenes-results`, ...)."""
        with self._session() as s:
            row = s.get(DumpRow, sha256)
        if row is None:
            raise NotFoundError(f"dump {sha256} is not stored")
        return row.kind

    def dump_path(self, sha256: str) -> Path:
        """Path of the stored upload with this digest."""
        path = self.dumps_dir / sha256
        if len(sha256) != 64 or not path.is_file():
            raise NotFoundError(f"dump {sha256} is not stored")
        return path

    def clean_dumps(self, grace: timedelta = timedelta(hours=1),
                    wait_s: float = 2.0) -> CleanReport:
        """Remove partial uploads (`.upload-*` of writers that died) and every dump that no job
        and no profile version references and that was not uploaded within `grace`; tighten
        the modes of files an older detcal left readable. Holds the dumps lock exclusively (no
        upload runs meanwhile); skipped when it is not free within `wait_s`."""
        with flocked(self.dumps_dir / LOCK_FILE, exclusive=True, wait_s=wait_s) as held:
            if not held:
                return CleanReport(skipped=True)
            partial = freed = 0
            for path in self.dumps_dir.glob(UPLOAD_PREFIX + "*"):
                freed += _unlink(path)
                partial += 1
            cutoff = utcnow() - grace
            stale = self._forget_unreferenced(cutoff)
            with self._session() as s:
                known = set(s.scalars(select(DumpRow.sha256)).all())
                known |= set(s.scalars(_referenced()).all())
            removed = 0
            for path in _dump_files(self.dumps_dir):
                if path.name not in known and (path.name in stale
                                               or _older(path, cutoff.timestamp())):
                    freed += _unlink(path)
                    removed += 1
                else:
                    tighten(path)
        return CleanReport(partial=partial, dumps=removed, bytes=freed)

    def _forget_unreferenced(self, cutoff) -> set[str]:
        """Delete the rows of unreferenced dumps last uploaded before `cutoff`; their digests
        (the condition is checked again by the DELETE itself, in one statement)."""
        unreferenced = (DumpRow.sha256.not_in(_referenced()),
                        func.coalesce(DumpRow.used_at, DumpRow.created_at) < cutoff)
        with self._tx() as s:
            stale = set(s.scalars(select(DumpRow.sha256).where(*unreferenced)).all())
            if stale:
                s.execute(delete(DumpRow).where(DumpRow.sha256.in_(stale), *unreferenced))
        return stale


def _referenced():
    """SELECT of every digest a job, a profile version or kept feedback references (never
    NULL)."""
    return union(select(JobRow.dump_sha256),
                 select(JobRow.gt_sha256).where(JobRow.gt_sha256.is_not(None)),
                 select(ProfileRow.dump_sha256).where(ProfileRow.dump_sha256.is_not(None)),
                 select(HealthRow.dump_sha256).where(HealthRow.dump_sha256.is_not(None)))


def _dump_files(directory: Path) -> Iterator[Path]:
    return (p for p in directory.iterdir() if DUMP_NAME.match(p.name))


def _unlink(path: Path) -> int:
    """Remove `path`; the bytes freed (0 if it was already gone)."""
    try:
        size = path.stat().st_size
        path.unlink()
        return size
    except FileNotFoundError:
        return 0


def _older(path: Path, cutoff: float) -> bool:
    try:
        return path.stat().st_mtime < cutoff
    except FileNotFoundError:
        return False
