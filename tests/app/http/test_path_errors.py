"""A bad path parameter is a 422 that names the parameter and the form it takes."""

from __future__ import annotations

from tests.app.conftest import ADMIN


def _msg(client, url: str) -> tuple[int, dict]:
    r = client.get(url, headers=ADMIN)
    return r.status_code, r.json()["detail"][0]


def test_a_truncated_job_id_is_told_what_a_job_id_looks_like(client):
    status, item = _msg(client, "/v1/jobs/3f2a9c1e")
    assert status == 422 and item["loc"] == ["path", "job_id"]
    assert item["msg"] == ("path parameter job_id: expected the job's id: 32 lowercase hex "
                           "digits, as POST /v1/fit returned it (got 8 characters)")
    assert "pattern" not in item["msg"]


def test_a_bad_version_or_name_names_the_parameter_and_its_form(client):
    status, item = _msg(client, "/v1/profiles/lidar/01")
    assert status == 422 and item["loc"] == ["path", "version"]
    assert item["msg"].startswith("path parameter version: a version is a plain positive "
                                  "integer")
    assert "expected version number (1, 2, ...)" in item["msg"]
    status, item = _msg(client, "/v1/profiles/.hidden")
    assert status == 422 and item["loc"] == ["path", "name"]
    assert item["msg"] == ("path parameter name: expected a profile name: 1-64 letters, "
                           "digits, `_ . -`, not starting with `.` or `-` (got 7 characters)")


def test_other_validation_errors_keep_their_message(client):
    status, item = _msg(client, "/v1/profiles/lidar/health?version=x")
    assert status == 422 and item["loc"] == ["query", "version"]
    assert not item["msg"].startswith("path parameter")
