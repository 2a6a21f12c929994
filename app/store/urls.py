"""Database URLs: which backend a URL names, and the driver detcal uses for it."""

from __future__ import annotations

from sqlalchemy.engine import URL, make_url

#: Postgres URLs without a driver (`postgresql://`, `postgres://`) get psycopg 3.
POSTGRES_DRIVER = "postgresql+psycopg"


def engine_url(url: str | URL) -> URL:
    """`url` as a SQLAlchemy URL, `postgresql://` and `postgres://` mapped to psycopg 3.

    Raises ValueError naming the URL's scheme when it is not a database URL at all.
    """
    try:
        parsed = make_url(url)
    except Exception as exc:  # noqa: BLE001 - SQLAlchemy raises ArgumentError
        scheme = str(url).split(":", 1)[0]
        raise ValueError(f"database_url is not a SQLAlchemy URL (scheme {scheme!r})") from exc
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername=POSTGRES_DRIVER)
    return parsed
