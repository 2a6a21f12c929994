"""Connection hygiene for `detcal serve`: uvicorn's httptools protocol with a header
deadline, a body deadline with a minimum rate, and a cap on the request head's size.

uvicorn times out only idle keep-alive connections; a client that sends its request line and
headers a byte at a time (slowloris), or trickles its body, holds a connection and its
memory for ever. `GuardedHttpToolsProtocol` closes such a connection:

- head: the request line and headers must be complete `header_timeout_s` after the
  connection opens, or after the first byte of a later request on a kept-alive connection
  (the idle wait in between is `keep_alive_s`); else `408` and the connection is closed.
  A head larger than `max_header_bytes` is a `431` and closed.
- body: it must arrive by `body_timeout_s` plus one second per `body_min_rate` bytes
  received after its headers, else the connection is closed (the app sees a disconnect).
  Time spent while the server itself has paused reading (the app is not consuming the body)
  does not count against the client.

uvicorn's own `limit_concurrency` (503 beyond that many connections and tasks) and
`timeout_keep_alive` are set from the same settings (`app.cli.serve`). The settings are read
from the `DETCAL_*` environment once per process (`ConnectionLimits.from_settings`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("detcal.connections")


@dataclass(frozen=True)
class ConnectionLimits:
    """The limits one protocol instance applies (seconds, bytes, bytes per second)."""

    header_timeout_s: float = 10.0
    body_timeout_s: float = 20.0
    body_min_rate: int = 8192
    max_header_bytes: int = 65536

    @classmethod
    def from_settings(cls) -> ConnectionLimits:
        """The limits of the process's settings (`DETCAL_HEADER_TIMEOUT_S`, ...)."""
        from app.settings import get_settings

        s = get_settings()
        return cls(s.header_timeout_s, s.body_timeout_s, s.body_min_rate, s.max_header_bytes)


_LIMITS: ConnectionLimits | None = None


def _limits() -> ConnectionLimits:
    global _LIMITS
    if _LIMITS is None:
        _LIMITS = ConnectionLimits.from_settings()
    return _LIMITS


def _reply(status: bytes) -> bytes:
    return (b"HTTP/1.1 " + status + b"\r\ncontent-type: text/plain; charset=utf-8\r\n"
            b"content-length: 0\r\nconnection: close\r\n\r\n")


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the deadlines of the module docstring."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.limits = _limits()
        self._deadline: asyncio.TimerHandle | None = None
        self._in_head = False      # between a request's first byte and its complete headers
        self._head_bytes = 0
        self._body_since = 0.0     # when the current body's headers completed
        self._body_bytes = 0
        self._in_body = False

    # -- timers ------------------------------------------------------------------------
    def _arm(self, delay: float, callback: Any) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(max(delay, 0.0), callback)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _start_head(self) -> None:
        self._in_head, self._head_bytes = True, 0
        self._arm(self.limits.header_timeout_s, self._head_timed_out)

    def _head_timed_out(self) -> None:
        self._deadline = None
        if self._in_head and not self.transport.is_closing():
            log.info("closed a connection from %s: request head not complete within %.0f s",
                     _peer(self.client), self.limits.header_timeout_s)
            self.transport.write(_reply(b"408 Request Timeout"))
            self.transport.close()

    def _body_due(self) -> float:
        return (self._body_since + self.limits.body_timeout_s
                + self._body_bytes / max(self.limits.body_min_rate, 1))

    def _body_check(self) -> None:
        self._deadline = None
        if not self._in_body or self.transport.is_closing():
            return
        now = time.monotonic()
        if self.flow.read_paused:   # the app is not reading: not the client's delay
            self._body_since += self.limits.body_timeout_s / 4
            self._arm(self.limits.body_timeout_s / 4, self._body_check)
            return
        due = self._body_due()
        if now < due:
            self._arm(due - now, self._body_check)
            return
        log.info("closed a connection from %s: request body slower than %d bytes/s after "
                 "%.0f s", _peer(self.client), self.limits.body_min_rate,
                 self.limits.body_timeout_s)
        self._in_body = False
        self.transport.close()

    # -- protocol hooks ----------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._start_head()   # a connection that sends nothing is closed too

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self._in_head = self._in_body = False
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._in_head:
            self._head_bytes += len(data)
        elif self._in_body:
            self._body_bytes += len(data)
        super().data_received(data)
        if (self._in_head and self._head_bytes > self.limits.max_header_bytes
                and not self.transport.is_closing()):
            log.info("closed a connection from %s: request head over %d bytes",
                     _peer(self.client), self.limits.max_header_bytes)
            self._disarm()
            self._in_head = False
            self.transport.write(_reply(b"431 Request Header Fields Too Large"))
            self.transport.close()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        if not self._in_head:   # the first byte of a later request on this connection
            self._start_head()

    def on_headers_complete(self) -> None:
        self._in_head = False
        self._in_body, self._body_since, self._body_bytes = True, time.monotonic(), 0
        self._arm(self.limits.body_timeout_s, self._body_check)
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self._in_body = False
        self._disarm()
        super().on_message_complete()


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "an unknown peer"
