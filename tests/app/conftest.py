"""Fixtures for the service's unit tests: a real app on a temporary SQLite file."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store
from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from tests.app import pg

TOKEN = "test-admin-token-0123456789"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="session")
def dump_given():
    """A small synthetic dump (sigmoid, 10 classes, 3 layers, given covariances)."""
    return synthetic_dump(n_frames=30, seed=0)


@pytest.fixture(scope="session")
def profile_json_given(dump_given) -> str:
    """Profile JSON fit on `dump_given` with its given covariances only (no other sources:
    a request must carry covariances)."""
    return fit_profile(dump_given, cov_source="given", other_sources=False).to_json()


@pytest.fixture(scope="session")
def profile_json_layers(dump_given) -> str:
    """Profile JSON fit on `dump_given` with the spread across decoder layers only."""
    return fit_profile(dump_given, cov_source="layers", other_sources=False).to_json()


@pytest.fixture(scope="session")
def conformal_json(dump_given) -> str:
    """Conformal regions with groups of >= 30 calibration points: 0.999 is out of reach."""
    return fit_profile(dump_given, cov_source="given", region_method="conformal",
                       min_group=30).to_json()


@pytest.fixture(scope="session")
def thesis_json(dump_given) -> str:
    """A thesis-method fit (global T, Σ + k·d·I, Gaussian regions), written as version 1."""
    text = fit_profile(dump_given, cov_source="given", score_method="temperature",
                       cov_method="depth", region_method="gaussian",
                       other_sources=False).to_json()
    assert json.loads(text)["schema_version"] == 1
    return text


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    """Settings on a fresh data directory with an admin token."""
    return Settings(data_dir=tmp_path / "data", admin_token=TOKEN)


@pytest.fixture
def seeded(settings: Settings, profile_json_given: str, profile_json_layers: str) -> Settings:
    """`settings` whose store holds `lidar` v1 (given, active) and `layers` v1."""
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("lidar", profile_json_given)
    store.add_profile("layers", profile_json_layers)
    store.close()
    return settings


@pytest.fixture
def client(seeded: Settings) -> Iterator[TestClient]:
    """A TestClient (lifespan run) over the seeded store."""
    with TestClient(create_app(seeded)) as c:
        yield c


@pytest.fixture
def empty_client(settings: Settings) -> Iterator[TestClient]:
    """A TestClient over an empty store."""
    with TestClient(create_app(settings)) as c:
        yield c


def _detection(dump, i: int, *, cov: bool = True, layers: bool = False) -> dict:
    """Request body of detection `i` of `dump` (final logits, final box, det_cov)."""
    det: dict = {"id": i, "logits": dump.det_logits[i, -1].tolist(),
                 "box": dump.det_boxes[i, -1].tolist()}
    if cov:
        det["covariance"] = dump.det_cov[i].tolist()
    if layers:
        det["layer_boxes"] = dump.det_boxes[i].tolist()
    return det


@pytest.fixture(scope="session")
def detection():
    """`detection(dump, i, cov=True, layers=False)`: request body of one dump detection."""
    return _detection


@pytest.fixture(scope="session")
def npz_bytes(tmp_path_factory, dump_given) -> bytes:
    """`dump_given` written as validation dump v1 (NPZ)."""
    from calibrators.io import save_dump

    path = tmp_path_factory.mktemp("dumps") / "val.npz"
    save_dump(path, dump_given)
    return path.read_bytes()


def wait_job(client, job_id: str, timeout_s: float = 60.0) -> dict:
    """Poll GET /v1/jobs/{id} until the job is finished (succeeded or failed)."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        body = client.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
        if body["state"] in ("succeeded", "failed") or time.monotonic() > deadline:
            return body
        time.sleep(0.05)


@pytest.fixture(scope="session")
def wait():
    """`wait(client, job_id)`: poll a fit job until it finishes."""
    return wait_job


# -- the store contract tests' fixtures: a SQLite file and a fresh schema of the shared
# -- throwaway Postgres cluster (tests/app/pg.py) -------------------------------------------
@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[pg.PostgresCluster]:
    """The shared throwaway Postgres cluster (started on first use)."""
    yield pg.acquire()
    pg.release()


@pytest.fixture(params=["sqlite", "postgres"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """URL of an empty database: a SQLite file, or a fresh schema on the Postgres cluster."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'detcal.db'}"
    return request.getfixturevalue("postgres_cluster").fresh_url()


@pytest.fixture
def store(url: str, tmp_path: Path) -> Iterator[Store]:
    s = Store(url, tmp_path / "dumps")
    yield s
    s.close()
