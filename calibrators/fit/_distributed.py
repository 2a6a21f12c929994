"""Run the per-part work of a streamed fit on a Dask cluster (the optional `dask` extra).

`dask_client(spec)` opens a `distributed.Client`: `local` or `local:N` starts a
`distributed.LocalCluster` of N worker processes (one thread each; N = 2 by default) and
closes it afterwards, `tcp://host:port` connects to a running scheduler (left running).
`Mapper(client)` maps a function over the parts: in this process without a client, with
`client.map` and `client.gather` with one; the reduction always happens on the caller.
Dask is imported only here, and only when a client is asked for.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from calibrators.core.errors import FieldError

_LOCAL = re.compile(r"^local(?::(\d+))?$")


def parse_dask_spec(spec: str) -> tuple[str, int | str]:
    """`("local", N)` for `local[:N]`, `("address", spec)` for `tcp://host:port`; a
    `FieldError` on `dask` otherwise."""
    match = _LOCAL.match(spec)
    if match:
        n = int(match.group(1) or 2)
        if not 1 <= n <= 256:
            raise FieldError("dask", f"dask: local:N needs 1 <= N <= 256 workers, got {n}")
        return "local", n
    if re.match(r"^(tcp|tls|inproc|ucx)://[^\s]+$", spec):
        return "address", spec
    raise FieldError("dask", f"dask must be 'local', 'local:N' or a scheduler address such as "
                             f"'tcp://host:8786', got {spec!r}")


@contextmanager
def dask_client(spec: str, *, processes: bool = True) -> Iterator[Any]:
    """A `distributed.Client` for `spec` (module docstring), closed on exit (with its local
    cluster). Raises ImportError naming the extra when dask is not installed."""
    kind, value = parse_dask_spec(spec)
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ImportError("the Dask fit needs the optional dependency: pip install "
                          "'detcal[dask]' (dask[distributed])") from None
    if kind == "address":
        try:
            client = Client(value, timeout=30)
        except OSError as exc:
            raise FieldError("dask", f"cannot reach the Dask scheduler at {value}: {exc}"
                             ) from None
        try:
            yield client
        finally:
            client.close()
        return
    with LocalCluster(n_workers=int(value), threads_per_worker=1, processes=processes,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


class Mapper:
    """`map(fn, items, **kwargs)`: `[fn(item, **kwargs) for item in items]`, here or on the
    workers of `client` (results gathered in order)."""

    def __init__(self, client: Any = None) -> None:
        self.client = client

    def map(self, fn: Callable[..., Any], *items: Iterable[Any], **kwargs: Any) -> list[Any]:
        return list(self.imap(fn, *items, **kwargs))

    def imap(self, fn: Callable[..., Any], *items: Iterable[Any], **kwargs: Any
             ) -> Iterator[Any]:
        """The results one at a time, in order, so the caller can reduce each as it comes
        (on a cluster the parts still run at once; each result is fetched when reached)."""
        if self.client is None:
            for args in zip(*items, strict=True):
                yield fn(*args, **kwargs)
            return
        futures = self.client.map(fn, *items, pure=False, **kwargs)
        for future in futures:
            yield future.result()
            future.release()
