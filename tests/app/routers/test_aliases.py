"""Aliases (set, move, calibrate by alias, champion = activate) and the audit log of writes."""

from __future__ import annotations

import pytest

from app.http.deps import token_id
from tests.app.conftest import ADMIN, TOKEN

AL = "/v1/profiles/lidar/aliases"


@pytest.fixture
def two_versions(client, profile_json_given):
    """`lidar` with versions 1 (active) and 2."""
    client.app.state.store.add_profile("lidar", profile_json_given.replace('"report"',
                                                                           '"report" ', 1))
    return client


def _calibrate(client, detection, dump, profile):
    return client.post("/v1/calibrate", json={"profile": profile, "frames": [
        {"detections": [detection(dump, 0)]}]})


def test_set_move_calibrate_by_alias_and_old_activate(two_versions, detection, dump_given):
    c = two_versions
    r = c.put(f"{AL}/challenger", headers=ADMIN, json={"version": 2})
    assert r.status_code == 200 and r.json()["id"] == "lidar@2"
    cal = _calibrate(c, detection, dump_given, "lidar@challenger")
    assert cal.status_code == 200 and cal.json()["profile"]["id"] == "lidar@2"
    assert _calibrate(c, detection, dump_given, "lidar").json()["profile"]["id"] == "lidar@1"
    assert _calibrate(c, detection, dump_given, "lidar@champion").json()["profile"]["id"] == \
        "lidar@1"
    r = c.put(f"{AL}/challenger", headers=ADMIN, json={"version": 1})     # moved
    assert _calibrate(c, detection, dump_given, "lidar@challenger").json()["profile"]["id"] == \
        "lidar@1"
    assert c.post("/v1/profiles/lidar/2/activate", headers=ADMIN).status_code == 200
    assert [(a["alias"], a["version"]) for a in c.get(AL).json()["aliases"]] == [
        ("champion", 2), ("challenger", 1)]
    assert c.put(f"{AL}/champion", headers=ADMIN, json={"version": 1}).status_code == 200
    assert c.get("/v1/profiles/lidar").json()["active_version"] == 1
    assert c.delete(f"{AL}/challenger", headers=ADMIN).json()["version"] == 1
    assert _calibrate(c, detection, dump_given, "lidar@challenger").status_code == 404

    entries = c.get("/v1/audit", headers=ADMIN).json()["entries"]
    assert [(e["action"], e["target"]) for e in reversed(entries)] == [
        ("alias", "lidar@challenger"), ("alias", "lidar@challenger"),
        ("activate", "lidar@champion"), ("activate", "lidar@champion"),
        ("alias.delete", "lidar@challenger")]
    assert {e["token_id"] for e in entries} == {token_id(TOKEN)}
    assert TOKEN not in str(entries)
    assert entries[1]["detail"] == {"version": 1, "previous": 2}


def test_writes_without_the_token_are_refused_and_not_logged(two_versions):
    c = two_versions
    for headers, code in (({}, 401), ({"Authorization": "Bearer wrong"}, 403)):
        assert c.put(f"{AL}/x", headers=headers, json={"version": 2}).status_code == code
        assert c.delete(f"{AL}/x", headers=headers).status_code == code
        assert c.post("/v1/profiles/lidar/2/activate", headers=headers).status_code == code
        assert c.get("/v1/audit", headers=headers).status_code == code
    assert c.get("/v1/audit", headers=ADMIN).json() == {"entries": [], "next_before": None}
    assert c.get("/v1/profiles/lidar").json()["active_version"] == 1


def test_a_fit_is_audited_once_with_its_job(client, npz_bytes, wait):
    r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)},
                    data={"name": "lidar"})
    assert r.status_code == 202
    wait(client, r.json()["job_id"])
    (entry,) = client.get("/v1/audit", headers=ADMIN, params={"action": "fit"}).json()["entries"]
    assert entry["target"] == "lidar" and entry["detail"]["job_id"] == r.json()["job_id"]


@pytest.mark.parametrize(("method", "path", "body", "loc"), [
    ("put", f"{AL}/9abc", {"version": 1}, ["path", "alias"]),
    ("put", f"{AL}/a!b", {"version": 1}, ["path", "alias"]),
    ("put", f"{AL}/x", {"version": 0}, ["body", "version"]),
    ("put", f"{AL}/x", {"version": "1"}, ["body", "version"]),
    ("put", f"{AL}/x", {}, ["body", "version"]),
    ("put", f"{AL}/x", {"version": 1, "extra": 1}, ["body", "extra"]),
    ("delete", f"{AL}/9abc", None, ["path", "alias"]),
    ("get", "/v1/audit?limit=0", None, ["query", "limit"]),
    ("get", "/v1/audit?action=nope", None, ["query", "action"]),
])
def test_bad_alias_and_audit_requests_name_the_field(client, method, path, body, loc):
    kwargs = {"headers": ADMIN} | ({} if body is None else {"json": body})
    r = getattr(client, method)(path, **kwargs)
    assert r.status_code == 422, r.text
    assert loc in [e["loc"] for e in r.json()["detail"]]


def test_the_champion_alias_cannot_be_deleted_409(client):
    r = client.delete(f"{AL}/champion", headers=ADMIN)
    assert r.status_code == 409, r.text
    assert r.json()["detail"][0]["loc"] == ["path", "alias"] and "activate" in r.text


def test_unknown_versions_names_and_aliases_are_404(client):
    assert client.put(f"{AL}/x", headers=ADMIN, json={"version": 7}).status_code == 404
    assert client.put("/v1/profiles/nope/aliases/x", headers=ADMIN,
                      json={"version": 1}).status_code == 404
    assert client.delete(f"{AL}/ghost", headers=ADMIN).status_code == 404
    assert client.get("/v1/profiles/nope/aliases").status_code == 404
    assert client.get("/v1/audit", headers=ADMIN).json()["entries"] == []


def test_the_audit_log_pages(client):
    for v in range(5):
        client.put(f"{AL}/a{v}", headers=ADMIN, json={"version": 1})
    page = client.get("/v1/audit", headers=ADMIN, params={"limit": 2}).json()
    assert [e["target"] for e in page["entries"]] == ["lidar@a4", "lidar@a3"]
    rest = client.get("/v1/audit", headers=ADMIN,
                      params={"limit": 10, "before": page["next_before"]}).json()
    assert [e["target"] for e in rest["entries"]] == ["lidar@a2", "lidar@a1", "lidar@a0"]
    assert rest["next_before"] is None
    assert len(client.get("/v1/audit", headers=ADMIN,
                          params={"name": "lidar"}).json()["entries"]) == 5
