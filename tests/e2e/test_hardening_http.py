"""Issue 11 against the real server: an unauthenticated upload is refused before its body is
sent, and odd methods, huge versions and non-finite JSON get 4xx answers on a live socket."""

from __future__ import annotations

import socket
import time

import pytest

from tests.e2e.conftest import ADMIN

DECLARED = 300 * 2**20          # 300 MB declared, under the 512 MB upload limit


def _raw_request(server, head: str, body: bytes = b"", timeout_s: float = 10.0) -> tuple[
        bytes, float]:
    """Send `head` and the first bytes of a body, never the rest; the server's answer (until
    it closes or `timeout_s`) and the seconds it took."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=timeout_s) as sock:
        start = time.monotonic()
        sock.sendall(head.encode() + body)
        chunks = []
        try:
            while chunk := sock.recv(65536):
                chunks.append(chunk)
                if b"\r\n\r\n" in b"".join(chunks) and b"}" in chunks[-1]:
                    break
        except TimeoutError:
            pass
        return b"".join(chunks), time.monotonic() - start


@pytest.mark.parametrize(("auth", "status"), [("", 401), ("Authorization: Bearer nope\r\n", 403)])
def test_an_unauthenticated_upload_is_answered_without_its_body(server, auth, status):
    boundary = "detcalboundary"
    head = (f"POST /v1/fit HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n{auth}"
            f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
            f"Content-Length: {DECLARED}\r\n\r\n")
    first = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"dump\"; "
             f"filename=\"val.npz\"\r\n\r\n").encode() + b"\0" * 64
    answer, took = _raw_request(server, head, first)
    assert answer.startswith(f"HTTP/1.1 {status} ".encode()), answer[:200]
    assert b"token" in answer and took < 5.0


def test_an_authenticated_upload_still_waits_for_its_body(server):
    """The control: with the token the server does wait for the declared body."""
    head = (f"POST /v1/fit HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
            f"Authorization: {ADMIN['Authorization']}\r\n"
            f"Content-Type: multipart/form-data; boundary=b\r\nContent-Length: {DECLARED}\r\n\r\n")
    answer, took = _raw_request(server, head, b"--b\r\n", timeout_s=1.5)
    assert answer == b"" and took >= 1.4


def test_odd_methods_and_huge_versions_on_a_live_socket(server, http):
    for i in range(20):
        r = http.request(f"M{i}", "/healthz")
        assert r.status_code in (400, 405), r.text
    r = http.get("/v1/profiles/lidar/9223372036854775808")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["path", "version"]
    assert http.get("/healthz").status_code == 200          # the connection is still usable
    metrics = http.get("/metrics").text
    assert 'method="M1"' not in metrics


def test_nan_in_meta_is_a_422_on_a_live_socket(server, http):
    doc = b'{"meta": {"x": NaN}, "results": {}}'
    r = http.post("/v1/calibrate/nuscenes", content=doc,
                  headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "meta", "x"]
