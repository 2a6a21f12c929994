"""The OpenAPI document speaks standard JSON Schema: a constraint pydantic could not place
(`ge`, `le`, `gt`, `lt` left as raw keys) is invisible to clients and to schema-driven
testers, which then send values the server refuses (a version of 0 looked valid)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

NON_STANDARD = {"ge", "le", "gt", "lt"}


def _schemas(node: Any, where: str = "") -> Iterator[tuple[str, dict]]:
    if isinstance(node, dict):
        yield where, node
        for key, value in node.items():
            if key not in ("examples", "example", "default"):
                yield from _schemas(value, f"{where}/{key}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _schemas(value, f"{where}/{i}")


def test_no_schema_carries_pydantic_constraint_names(client):
    spec = client.get("/openapi.json").json()
    bad = [f"{where}: {sorted(NON_STANDARD & set(node))}" for where, node in _schemas(spec)
           if "type" in node and NON_STANDARD & set(node)]
    assert not bad, bad


def test_version_parameters_state_their_minimum(client):
    spec = client.get("/openapi.json").json()
    version = next(p for p in spec["paths"]["/v1/profiles/{name}/{version}"]["get"]["parameters"]
                   if p["name"] == "version")
    assert version["schema"]["minimum"] == 1
