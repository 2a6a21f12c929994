"""`?fields=`: the summary form of jobs, profiles and health answers."""

from __future__ import annotations

import json

from tests.app.conftest import ADMIN


def test_fields_keep_only_the_named_keys_of_a_profile_version(client):
    full = client.get("/v1/profiles/lidar/1", headers=ADMIN)
    assert full.status_code == 200
    r = client.get("/v1/profiles/lidar/1?fields=version,profile.temperature", headers=ADMIN)
    assert r.status_code == 200, r.text
    assert r.json() == {"version": 1,
                        "profile": {"temperature": full.json()["profile"]["temperature"]}}
    assert int(r.headers["content-length"]) == len(r.content) < len(full.content) / 50


def test_fields_trim_each_item_of_a_list_and_the_health_document(client):
    r = client.get("/v1/profiles?fields=name", headers=ADMIN)
    assert r.status_code == 200, r.text
    items = r.json() if isinstance(r.json(), list) else next(iter(r.json().values()))
    assert items and all(set(item) == {"name"} for item in items), r.json()
    r = client.get("/v1/profiles/lidar/health?fields=status,window.frames", headers=ADMIN)
    assert r.status_code == 200, r.text
    assert set(r.json()) == {"status", "window"} and set(r.json()["window"]) == {"frames"}


def test_an_unknown_or_malformed_field_is_a_422_naming_it(client):
    r = client.get("/v1/profiles/lidar/1?fields=version,nope", headers=ADMIN)
    assert r.status_code == 422
    item = r.json()["detail"][0]
    assert item["loc"] == ["query", "fields"] and "unknown field 'nope'" in item["msg"]
    assert "version" in item["msg"]                       # ... and lists what there is
    for bad in ("", "a,,b", "a b", ".a"):
        r = client.get("/v1/profiles/lidar/1", params={"fields": bad}, headers=ADMIN)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "fields"]


def test_fields_is_documented_on_the_summary_routes_only(client):
    spec = json.loads(client.get("/openapi.json").text)

    def takes_fields(path: str) -> bool:
        return any(p["name"] == "fields" for p in spec["paths"][path]["get"].get(
            "parameters", []))

    for path in ("/v1/jobs/{job_id}", "/v1/profiles/{name}/{version}",
                 "/v1/profiles/{name}/health", "/v1/profiles"):
        assert takes_fields(path), path
    assert not takes_fields("/healthz")
