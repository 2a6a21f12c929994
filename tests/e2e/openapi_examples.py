"""The requests the OpenAPI examples make (tests/e2e/test_docs_tour.py sends them): every
example of the JSON request bodies (the body schemas' `examples`, the examples of their parts
swapped into the first body) and of the parameters, as (method, path, query, body)."""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from typing import Any


def _resolve(spec: dict, node: dict) -> dict:
    while "$ref" in node:
        node = spec["components"]["schemas"][node["$ref"].rsplit("/", 1)[1]]
    return node


def _examples(node: dict) -> list:
    """A schema's or parameter's own examples (also those of its anyOf/oneOf branches)."""
    out = list(node.get("examples", []) if isinstance(node.get("examples"), list) else [])
    if isinstance(node.get("examples"), dict):          # media type / parameter: name -> {value}
        out += [e["value"] for e in node["examples"].values() if "value" in e]
    if "example" in node:
        out.append(node["example"])
    for branch in node.get("anyOf", []) + node.get("oneOf", []):
        out += _examples(branch)
    return out


def _parts(spec: dict, schema: dict, value: Any, path: tuple) -> Iterator[tuple[tuple, Any]]:
    """(path, example) of every sub-schema of `schema` below the body, walking `value`."""
    schema = _resolve(spec, schema)
    if path:
        for ex in _examples(schema):
            yield path, ex
    for branch in schema.get("anyOf", []) + schema.get("oneOf", []):
        if "$ref" in branch or "properties" in branch or "items" in branch:
            yield from _parts(spec, {**branch, "examples": []}, value, path)
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for key, sub in props.items():
            yield from _parts(spec, sub, value.get(key), (*path, key))
        extra = schema.get("additionalProperties")
        if isinstance(extra, dict):
            for key in value.keys() - props.keys():
                yield from _parts(spec, extra, value[key], (*path, key))
    elif isinstance(value, list) and value and isinstance(schema.get("items"), dict):
        yield from _parts(spec, schema["items"], value[0], (*path, 0))


def _set(body: Any, path: tuple, value: Any) -> Any:
    body = copy.deepcopy(body)
    node = body
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return body


# Path parameters that have no example of their own, for an operation that has some.
FILL = {"version": "1"}


def openapi_requests(spec: dict) -> list[tuple[str, str, dict, Any]]:
    """(method, path, query, json body) for every example of the JSON request bodies and of
    the parameters; refuses an operation it cannot fill."""
    requests: list[tuple[str, str, dict, Any]] = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            media = op.get("requestBody", {}).get("content", {}).get("application/json")
            bodies: list[Any] = []
            if media is not None:
                schema = media["schema"]
                bodies = _examples(media) + _examples(_resolve(spec, schema))
                assert bodies, f"{method.upper()} {path}: a JSON body without an example"
                for part_path, ex in _parts(spec, schema, bodies[0], ()):
                    bodies.append(_set(bodies[0], part_path, ex))
            params = op.get("parameters", [])
            with_examples = [(p, ex) for p in params for ex in _examples(p)
                             + _examples(p.get("schema", {}))]
            if not bodies and not with_examples:
                continue
            defaults = {}
            for p in params:
                if p.get("required"):
                    own = _examples(p) + _examples(p.get("schema", {}))
                    assert own or p["name"] in FILL, f"{method.upper()} {path}: no {p['name']}"
                    defaults[p["name"]] = str(own[0]) if own else FILL[p["name"]]
            body = bodies[0] if bodies else None
            variants = [(defaults, b) for b in bodies]
            variants += [({**defaults, p["name"]: ex}, body) for p, ex in with_examples]
            for values, b in variants:
                url = path
                query = {}
                for p in params:
                    if p["name"] not in values:
                        continue
                    if p["in"] == "path":
                        url = url.replace("{" + p["name"] + "}", str(values[p["name"]]))
                    else:
                        query[p["name"]] = values[p["name"]]
                key = (method, url, json.dumps(query, sort_keys=True), json.dumps(b))
                if key not in {(m, u, json.dumps(q, sort_keys=True), json.dumps(x))
                               for m, u, q, x in requests}:
                    requests.append((method, url, query, b))
    return requests
