"""In-memory cache of parsed profiles; stored versions are immutable, so a version never goes stale.

The active *pointer* (alias `champion`) and every other alias are read from the store, so an
activation or alias move by another worker process or a finished fit is seen by the next
request. Aliases are read on every lookup (one indexed read); active versions are kept until
the store's commit marker moves (SQLite: any commit by anyone, `app.store.changes`), and read
on every lookup where the store has no marker (Postgres).

A stored profile is 3-D (`CalibrationProfile`) or 2-D (`calibrators.boxes2d.Profile2D`, parsed
with a lazy import: the 3-D paths never load the 2-D library); its JSON's `kind` says which
(`calibrators.core.vocab.profile_kind`). `resolve` hands out the kinds its caller serves, 3-D
by default: any other is a 422 at the caller's `loc` saying what the profile is.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

from app.http.errors import RequestError
from app.schemas.types import parse_profile_ref
from app.store import NotFoundError, ProfileRecord, Store
from calibrators.core.vocab import PROFILE_KINDS
from calibrators.profile import read_profile

#: What the 3-D routes serve (`ProfileCache.resolve`'s default).
THREE_D = ("3d",)


@dataclass(frozen=True)
class LoadedProfile:
    """A stored profile version, its parsed profile (a `CalibrationProfile`, or a `Profile2D`
    when `kind` is `boxes2d`) and the `ProfileRef` body of responses (built once: a calibrate
    response names its profile on every request)."""

    record: ProfileRecord
    profile: Any
    kind: str = field(init=False)   # the profile's kind (`PROFILE_KINDS`), read once
    ref_body: dict[str, object] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = self.record
        object.__setattr__(self, "kind", str(self.profile.kind))
        object.__setattr__(self, "ref_body", {"id": r.ref, "name": r.name,
                                              "version": r.version, "sha256": r.sha256})

    def ref(self) -> dict[str, object]:
        """The `ProfileRef` body of responses (a copy: callers may add to it)."""
        return dict(self.ref_body)


class ProfileCache:
    """Parsed profiles keyed by `(name, version)`, resolved against the store's active pointer."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self._cache: dict[tuple[str, int], LoadedProfile] = {}
        self._lock = threading.Lock()
        self._active: dict[str, int | None] = {}   # active versions read at `_marker`
        self._marker: int | None = None
        self._changes = store.change_marker()   # None: read the active version every time

    def load_active(self) -> list[LoadedProfile]:
        """Parse and cache the active version of every name (at start-up)."""
        loaded = []
        for name, version in self.store.active_versions().items():
            loaded.append(self._version(name, version))
        return loaded

    def cached(self) -> list[LoadedProfile]:
        """Everything parsed so far."""
        with self._lock:
            return list(self._cache.values())

    def resolve(self, ref: str | None, default: str, loc: tuple[str, ...] = ("body", "profile"),
                kinds: tuple[str, ...] = THREE_D) -> LoadedProfile:
        """The profile for `name` (active version), `name@version` or `name@alias`; 404 if
        unknown, 422 naming `loc` if `ref` is not a name or its version or alias is malformed,
        or if the profile is not of one of `kinds` (`PROFILE_KINDS`)."""
        loaded = self._resolve(ref, default, loc)
        if loaded.kind not in kinds:
            raise RequestError(list(loc), kind_error(loaded, kinds),
                               kind="value_error.profile_kind")
        return loaded

    def _resolve(self, ref: str | None, default: str, loc: tuple[str, ...]) -> LoadedProfile:
        try:
            name, number, alias = parse_profile_ref(default if ref is None else ref)
        except ValueError as exc:
            raise RequestError(list(loc), str(exc)) from None
        if number is not None:
            return self._version(name, number)
        if alias is not None:
            return self._version(name, self.store.alias_version(name, alias))
        version = self._active_version(name)
        if version is None:
            raise NotFoundError(f"profile {name!r} does not exist")
        return self._version(name, version)

    def _active_version(self, name: str) -> int | None:
        """The store's active version of `name`, read again only after a commit."""
        # read first: a commit after it is seen next time
        marker = None if self._changes is None else self._changes.value()
        with self._lock:
            if marker is not None and marker == self._marker and name in self._active:
                return self._active[name]
        version = self.store.active_version(name)
        if marker is not None:
            with self._lock:
                if marker != self._marker:
                    self._active, self._marker = {}, marker
                self._active[name] = version
        return version

    def _version(self, name: str, version: int) -> LoadedProfile:
        key = (name, version)
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        record = self.store.get(name, version)
        loaded = parse_record(record)
        with self._lock:
            self._cache[key] = loaded
        return loaded


def parse_record(record: ProfileRecord) -> LoadedProfile:
    """A stored version parsed as its kind says (`read_profile`; ValueError naming a bad
    key)."""
    return LoadedProfile(record, read_profile(record.json))


def kind_error(loaded: LoadedProfile, kinds: tuple[str, ...]) -> str:
    """Why `loaded` cannot serve a route of `kinds`."""
    what = {"3d": "a 3-D profile", "boxes2d": "a 2-D (boxes2d) profile"}
    wanted = " or ".join(what[k] for k in kinds if k in PROFILE_KINDS)
    return (f"profile {loaded.record.ref} is {what[loaded.kind]}; this route serves "
            f"{wanted}")
