"""Issue 25, item 5: the audit log's `previous` is read in the write's own transaction, so
under concurrent activations and alias moves every entry names the version the pointer
really held just before it (checked against the history the log itself orders)."""

from __future__ import annotations

import random
import threading

from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store
from tests.app.conftest import ADMIN

AL = "/v1/profiles/lidar/aliases"
VERSIONS = (1, 2, 3, 4)


def _ops(seed: int, n: int) -> list[tuple[str, str, int]]:
    """`n` random writes: activate, PUT an alias (champion included) or DELETE one."""
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        kind = rng.choice(("activate", "put", "put", "delete"))
        out.append((kind, rng.choice(("champion", "challenger", "canary")),
                    rng.choice(VERSIONS)))
    return out


def _run(client: TestClient, ops: list[tuple[str, str, int]], codes: list[int]) -> None:
    for kind, alias, version in ops:
        if kind == "activate":
            r = client.post(f"/v1/profiles/lidar/{version}/activate", headers=ADMIN)
        elif kind == "put":
            r = client.put(f"{AL}/{alias}", headers=ADMIN, json={"version": version})
        elif alias == "champion":
            continue
        else:
            r = client.delete(f"{AL}/{alias}", headers=ADMIN)
        codes.append(r.status_code)


def test_previous_is_right_for_every_entry_under_8_threads(settings: Settings,
                                                            profile_json_given: str) -> None:
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    for v in VERSIONS:   # four distinct versions of lidar; v1 active
        store.add_profile("lidar", profile_json_given.replace('"report"', '"report"' + " " * v, 1))
    store.close()
    codes: list[int] = []
    with TestClient(create_app(settings)) as client:
        threads = [threading.Thread(target=_run, args=(client, _ops(seed, 25), codes))
                   for seed in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        final = {a["alias"]: a["version"] for a in client.get(AL).json()["aliases"]}
        entries = client.get("/v1/audit", headers=ADMIN, params={"limit": 1000}).json()
    assert set(codes) <= {200, 404} and codes.count(200) > 100, sorted(set(codes))
    entries = sorted(entries["entries"], key=lambda e: e["id"])
    assert len(entries) == codes.count(200)
    state: dict[str, int] = {"champion": 1}   # the true history, replayed in commit order
    wrong = []
    for e in entries:
        alias = e["target"].split("@", 1)[1]
        if e["detail"].get("previous") != state.get(alias):
            wrong.append((e["id"], e["action"], alias, e["detail"], state.get(alias)))
        if e["action"] == "alias.delete":
            state.pop(alias)
        else:
            state[alias] = e["detail"]["version"]
    assert not wrong, f"{len(wrong)} of {len(entries)} entries have a wrong previous: {wrong[:5]}"
    assert state == final
