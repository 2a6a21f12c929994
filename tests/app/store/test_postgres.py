"""Postgres specifics: URL mapping, several processes on one database, the app on Postgres.

The store contract itself runs on both backends in test_store.py; this module adds what only
matters with a server database shared by several processes (each `Store` here stands for one
process: its own engine and connection pool).
"""

from __future__ import annotations

import io
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text

from app.main import create_app
from app.settings import Settings
from app.store import Store
from app.store.urls import engine_url
from tests.app import pg
from tests.app.conftest import ADMIN, TOKEN


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[pg.PostgresCluster]:
    """The shared throwaway Postgres cluster (started on first use)."""
    yield pg.acquire()
    pg.release()


@pytest.fixture
def pg_url(postgres_cluster: pg.PostgresCluster) -> str:
    """`postgresql+psycopg://` URL of a new, empty schema."""
    return postgres_cluster.fresh_url()


@pytest.mark.parametrize(("given", "expected"), [
    ("postgresql://u:pw@db:5432/detcal", "postgresql+psycopg://u:pw@db:5432/detcal"),
    ("postgres://u@db/detcal", "postgresql+psycopg://u@db/detcal"),
    ("postgresql+psycopg://u@db/detcal", "postgresql+psycopg://u@db/detcal"),
    ("sqlite:////data/detcal.db", "sqlite:////data/detcal.db"),
])
def test_urls_map_plain_postgres_to_psycopg(given: str, expected: str) -> None:
    assert engine_url(given).render_as_string(hide_password=False) == expected


def test_a_non_url_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="database_url is not a SQLAlchemy URL"):
        engine_url("not a url")


def test_plain_postgresql_url_from_the_environment(pg_url: str, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    plain = pg_url.replace("postgresql+psycopg://", "postgresql://")
    monkeypatch.setenv("DETCAL_DATABASE_URL", plain)
    settings = Settings(data_dir=tmp_path)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    try:
        assert store.backend == "postgresql" and store.engine.dialect.driver == "psycopg"
        assert store.ping()
        assert store.add_profile("lidar", "{}").version == 1
    finally:
        store.close()
    assert not (tmp_path / "detcal.db").exists()              # nothing fell back to SQLite


def test_timestamps_come_back_timezone_aware(pg_url: str, tmp_path: Path) -> None:
    store = Store(pg_url, tmp_path / "dumps")
    try:
        record = store.add_profile("lidar", "{}")
        assert record.created_at.utcoffset() is not None
        assert store.get("lidar", 1).created_at == record.created_at
    finally:
        store.close()


def _stores(url: str, tmp_path: Path, n: int) -> list[Store]:
    """`n` stores on one database, created at once (as `n` server processes starting)."""
    stores: list[Store | None] = [None] * n
    start = threading.Barrier(n)

    def open_store(i: int) -> None:
        start.wait()
        stores[i] = Store(url, tmp_path / "dumps")

    threads = [threading.Thread(target=open_store, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(stores), "a store failed to open (schema creation raced?)"
    return stores  # type: ignore[return-value]


def test_processes_share_versions_jobs_and_the_active_pointer(pg_url: str,
                                                             tmp_path: Path) -> None:
    """Three 'processes' fitting and claiming at once: distinct versions, each job once."""
    stores = _stores(pg_url, tmp_path, 3)
    try:
        sha = stores[0].put_dump(io.BytesIO(b"d"), "npz").sha256
        jobs = {stores[0].create_job("lidar", {}, sha).id for _ in range(6)}
        claimed: list[str] = []
        errors: list[Exception] = []
        start = threading.Barrier(len(stores))

        def work(store: Store, k: int) -> None:
            start.wait()
            try:
                for i in range(4):
                    store.add_profile("lidar", json.dumps({"k": k, "i": i}), activate=i == 3)
                while (job := store.claim_job()) is not None:
                    claimed.append(job.id)
            except Exception as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=work, args=(s, k)) for k, s in enumerate(stores)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors
        versions = stores[1].versions("lidar")
        assert [v.version for v in versions] == list(range(1, 13))
        assert sum(v.active for v in versions) == 1
        assert stores[2].active_version("lidar") == next(v.version for v in versions if v.active)
        assert sorted(claimed) == sorted(jobs)
        with stores[0].engine.connect() as conn:               # one pointer row per name
            assert conn.execute(text("SELECT count(*) FROM active_profiles")).scalar() == 1
    finally:
        for s in stores:
            s.close()


def test_app_fits_and_serves_on_postgres(pg_url: str, tmp_path: Path, npz_bytes: bytes,
                                         dump_given, detection, wait) -> None:
    """POST /v1/fit on a Postgres store, the job succeeds, /v1/calibrate serves the version."""
    settings = Settings(data_dir=tmp_path / "data", admin_token=TOKEN,
                        database_url=pg_url.replace("postgresql+psycopg://", "postgresql://"))
    with TestClient(create_app(settings)) as client:
        assert client.get("/readyz").json()["checks"]["store"] == "ok"   # no profile yet
        r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                        data={"name": "lidar"})
        assert r.status_code == 202, r.text
        job = wait(client, r.json()["job_id"])
        assert job["state"] == "succeeded", job
        assert job["profile"]["id"] == "lidar@1"
        body = {"profile": "lidar", "frames": [
            {"frame_id": "f0", "detections": [detection(dump_given, i) for i in range(5)]}]}
        r = client.post("/v1/calibrate", json=body)
        assert r.status_code == 200, r.text
        out = r.json()
        assert out["profile"]["id"] == "lidar@1"
        dets = out["frames"][0]["detections"]
        assert len(dets) == 5 and all(0.0 < d["score"] < 1.0 for d in dets)
        assert all(d["score"] != d["score_raw"] for d in dets)
    with TestClient(create_app(settings)) as client:           # a restart finds it again
        assert client.get("/v1/profiles/lidar").json()["active_version"] == 1
        assert client.get("/readyz").status_code == 200
