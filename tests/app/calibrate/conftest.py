"""A 2-D profile for the calibrate tests: `cam2d`, fit on a synthetic COCO pair
(`calibrators.boxes2d.synthetic_coco`), in the seeded store beside the 3-D `lidar` and
`layers`."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store
from calibrators.boxes2d import (
    Detections2D,
    Profile2D,
    fit_profile_2d,
    parse_instances,
    synthetic_coco,
)


@pytest.fixture(scope="session")
def coco_pair() -> tuple[list[dict], dict]:
    """`(results, instances)` of 400 synthetic images (640 x 480), with `layer_boxes`."""
    results, instances = synthetic_coco(400, seed=0)
    return results, instances


@pytest.fixture(scope="session")
def profile_2d(coco_pair) -> Profile2D:
    results, instances = coco_pair
    return fit_profile_2d(Detections2D.from_coco(results), parse_instances(instances),
                          holdout=0.25)


def serving(settings: Settings, name: str, profile: Profile2D) -> Iterator[TestClient]:
    """A client of the app over `settings`' store with `profile` added as `name`."""
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile(name, profile.to_json())
    store.close()
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture
def client_2d(seeded: Settings, profile_2d: Profile2D) -> Iterator[TestClient]:
    """The seeded store (`lidar`, `layers`: 3-D) with `cam2d` v1, a 2-D profile."""
    yield from serving(seeded, "cam2d", profile_2d)
