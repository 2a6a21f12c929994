"""The profile cache sees every activation at the next lookup, from this store or from another
connection (another worker process), though it reads the active pointer only after commits."""

from __future__ import annotations

from app.calibrate.cache import ProfileCache
from app.settings import Settings
from app.store import Store


def test_activation_elsewhere_is_seen_at_the_next_lookup(tmp_path, profile_json_given,
                                                          profile_json_layers):
    settings = Settings(data_dir=tmp_path)
    mine = Store(settings.sqlalchemy_url, settings.dumps_dir)
    other = Store(settings.sqlalchemy_url, settings.dumps_dir)   # as another worker's store
    try:
        mine.add_profile("lidar", profile_json_given)
        cache = ProfileCache(mine)
        assert cache.resolve(None, "lidar").record.version == 1
        marker = mine.commit_marker()
        assert cache.resolve(None, "lidar").record.version == 1
        assert mine.commit_marker() == marker   # lookups commit nothing: the pointer is cached
        other.add_profile("lidar", profile_json_layers, activate=True)   # v2
        assert mine.commit_marker() != marker
        assert cache.resolve(None, "lidar").record.version == 2
        other.activate("lidar", 1)
        assert cache.resolve(None, "lidar").record.version == 1
        mine.activate("lidar", 2)                                  # through this process's pool
        assert cache.resolve(None, "lidar").record.version == 2
        assert cache.resolve("lidar@1", "lidar").record.version == 1
    finally:
        mine.close()
        other.close()


def test_stores_without_a_marker_read_the_pointer_every_time(tmp_path, profile_json_given):
    store = Store("sqlite://", tmp_path / "dumps")    # in memory: no file to watch
    try:
        assert store.commit_marker() is None
        store.add_profile("lidar", profile_json_given)
        assert ProfileCache(store).resolve(None, "lidar").record.version == 1
    finally:
        store.close()
