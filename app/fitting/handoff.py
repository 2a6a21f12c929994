"""The dump `POST /v1/fit` parsed to check it, handed to the job that fits it: an upload is
parsed once, not once by the request and again by the job.

The request puts the checked dump here under its stored content hash; the job runner of the
same process takes it when it claims that job. A job claimed by another process (several
workers on one store), or one whose dump was pushed out by a newer upload, parses the stored
file as before, so the handoff only ever saves work. It holds at most `capacity` dumps (one
by default: no more memory than the request held while checking it)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

Key = tuple[str, str | None]   # (stored dump sha256, ground-truth sha256 or None)


class ParsedUploads:
    """Parsed fit inputs by `Key`, the newest `capacity` kept."""

    def __init__(self, capacity: int = 1) -> None:
        self.capacity = capacity
        self._items: OrderedDict[Key, Any] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, key: Key, dump: Any) -> None:
        """Keep `dump` for the job of `key`, dropping the oldest beyond `capacity`."""
        with self._lock:
            self._items[key] = dump
            self._items.move_to_end(key)
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)

    def take(self, key: Key) -> Any | None:
        """The dump kept for `key`, removed from here; None when there is none."""
        with self._lock:
            return self._items.pop(key, None)

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
