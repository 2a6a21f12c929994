"""First start (`detcal serve --bootstrap`, as `make run` does): token file, default profile."""

from __future__ import annotations

import stat

from app.fitting.bootstrap import ensure_admin_token, ensure_default_profile, shipped_dump
from app.settings import Settings
from app.store import Store
from calibrators.profile import CalibrationProfile


def test_default_profile_from_the_shipped_lidar_dump(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", admin_token="t" * 24)
    said: list[str] = []
    assert shipped_dump("lidar") is not None
    record = ensure_default_profile(settings, say=said.append)
    assert record is not None and record.ref == "lidar@1"
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    try:
        active = store.active("lidar")
        profile = CalibrationProfile.from_json(active.json)
        assert active.version == 1
        # the dump is kept content-addressed, so the fit can be reproduced
        assert store.dump_path(active.dump_sha256).is_file()
    finally:
        store.close()
    assert profile.cov_source == "layers" and profile.temperature > 0
    assert all(k >= 0 for k in profile.depth_k.values())
    stored = [line for line in said if "stored profile lidar@1" in line]
    # make run says which method each stage chose, as `detcal fit` does
    assert stored and f"scores {profile.score_method}, covariance {profile.cov_method}, " \
        f"regions {profile.region_method}" in stored[0]
    # a second start finds the profile and fits nothing
    assert ensure_default_profile(settings, say=said.append) is None


def test_admin_token_file_is_private_and_only_made_without_a_configured_token(tmp_path):
    settings = Settings(data_dir=tmp_path / "data")
    path = ensure_admin_token(settings, say=lambda _: None)
    assert path is not None and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(path.read_text().strip()) >= 32
    configured = Settings(data_dir=tmp_path / "other", admin_token="x" * 24)
    assert ensure_admin_token(configured, say=lambda _: None) is None


def test_every_start_says_where_the_admin_token_is(tmp_path):
    said: list[str] = []
    first = ensure_admin_token(Settings(data_dir=tmp_path / "data"), say=said.append)
    warm = ensure_admin_token(Settings(data_dir=tmp_path / "data"), say=said.append)
    assert first == warm and warm is not None
    assert len(said) == 2 and all(str(warm.resolve()) in line for line in said), said
    said.clear()
    ensure_admin_token(Settings(data_dir=tmp_path / "env", admin_token="x" * 24), said.append)
    assert said == ["detcal: the admin token is the one set in DETCAL_ADMIN_TOKEN"]
