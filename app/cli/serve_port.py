"""Is the address `detcal serve` is about to listen on free? Asked before anything is printed
or fitted, so that a busy port is one clear error instead of a log that first says it serves."""

from __future__ import annotations

import errno
import socket


def bind_error(host: str, port: int) -> str | None:
    """None when `host:port` can be bound (as uvicorn binds it, with SO_REUSEADDR), else one
    sentence saying why not and what to do."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return (f"detcal: cannot serve on http://{host}:{port}/: the port is already "
                        f"in use (another server?); stop it or choose another port with "
                        f"--port or DETCAL_PORT")
            return f"detcal: cannot serve on http://{host}:{port}/: {exc.strerror or exc}"
    return None
