"""Hostile Arrow bodies on POST /v1/calibrate get 4xx naming the column (or 413 for the caps),
never a 500: the four 500s and the three bombs of issue 25, compression within the inflated
cap, identity columns copied out of the client's buffers and capped, seeded mutations of valid
2-D batches sent to a 2-D profile. The streams that crashed
the server or echoed its memory are sent to a real server in tests/e2e/test_arrow_bombs.py."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators.core.errors import FieldError
from calibrators.io.arrow_batch import ARROW_STREAM, read_stream
from calibrators.io.arrow_headers import batch_header, inflated_bytes
from calibrators.io.arrow_safe import MAX_ID_BYTES, plain_stream
from tests import arrow_bombs as bombs
from tests.arrow_mutator import (
    COMPRESSIONS,
    buffer_roles,
    messages,
    mutate,
    request_batch,
    request_batch_2d,
    stream,
)

CAL = "/v1/calibrate"
ARROW = {"content-type": ARROW_STREAM}


def _post(client, data: bytes, query: str = ""):
    return client.post(CAL + query, content=data, headers=ARROW)


@pytest.mark.parametrize(("build", "status", "loc"), [
    (bombs.zero_rows, 422, ["body"]),
    (bombs.dictionary_index, 422, ["body", "label"]),
    (bombs.zstd_prefix, 422, ["body", "logits"]),
    (bombs.short_id, 422, ["body", "id"]),
    (bombs.zstd_bomb, 413, ["body"]),
    (bombs.frame_id_bomb, 422, ["body", "frame_id", 0]),
])
def test_the_issue_500s_and_bombs_are_4xx(client, dump_given, build, status, loc):
    r = _post(client, build(dump_given))
    assert r.status_code == status, r.text
    assert r.json()["detail"][0]["loc"] == loc, r.json()


def test_five_million_rows_in_a_small_body_are_a_413_from_the_header(client):
    data = bombs.rows_bomb()
    assert len(data) < 24 * 1024
    r = _post(client, data)
    assert r.status_code == 413 and "5000000 rows" in r.text, r.text


@pytest.mark.parametrize("codec", ["zstd", "lz4"])
def test_compressed_streams_within_the_cap_answer_as_uncompressed(client, dump_given, codec):
    batch = request_batch(dump_given, 40)
    plain = _post(client, stream([batch]), "?levels=0.9")
    packed = _post(client, stream([batch[:15], batch[15:]], codec), "?levels=0.9")
    assert plain.status_code == packed.status_code == 200, packed.text
    assert pa.ipc.open_stream(plain.content).read_all().equals(
        pa.ipc.open_stream(packed.content).read_all())


def test_frame_id_is_capped_and_echoed_from_a_copy(client, dump_given):
    batch = request_batch(dump_given, 4)
    ok = ["a" * MAX_ID_BYTES, "b", "c", "d"]
    r = _post(client, stream([batch.set_column(0, "frame_id", pa.array(ok))]))
    assert r.status_code == 200, r.text
    assert pa.ipc.open_stream(r.content).read_all()["frame_id"].to_pylist() == ok
    long = ["a", "b", "c" * (MAX_ID_BYTES + 1), "d"]
    r = _post(client, stream([batch.set_column(0, "frame_id", pa.array(long))]))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "frame_id", 2]
    data = stream([batch])
    body = pa.py_buffer(data)
    read = read_stream(body.to_pybytes())
    for name in ("frame_id", "id"):
        for buf in read.column(name).buffers():
            assert buf is None or not (body.address <= buf.address < body.address + len(data))


def test_an_identity_list_may_not_amplify_the_echo(client, dump_given):
    batch = request_batch(dump_given, 4)
    i = batch.schema.get_field_index("id")
    for width, status in ((30, 200), (40, 422)):   # 240 and 320 bytes of int64 per row
        ids = pa.FixedSizeListArray.from_arrays(pa.array(np.arange(4 * width)), width)
        r = _post(client, stream([batch.set_column(i, "id", ids)]))
        assert r.status_code == status, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "id"]


@pytest.mark.parametrize(("column", "values"), [
    ("id", pa.array([True, False, True, False])),
    ("id", pa.array([b"x"] * 4, pa.binary())),
    ("frame_id", pa.array([{"a": {"b": [1]}}] * 4)),
])
def test_other_column_types_are_refused_by_name(client, dump_given, column, values):
    batch = request_batch(dump_given, 4)
    i = batch.schema.get_field_index(column)
    r = _post(client, stream([batch.set_column(i, column, values)]))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", column], r.text


def test_the_inflated_cap_is_checked_before_decoding(dump_given):
    batch = request_batch(dump_given, 300)
    data = stream([batch, batch], "zstd")
    msgs = [m for m in messages(data) if m.kind == "record batch"]
    body = memoryview(data)[msgs[0].body_at:msgs[0].body_at + msgs[0].body_len]
    one = inflated_bytes(msgs[0].header, body)
    assert one >= batch.nbytes and msgs[0].header.codec == "zstd"
    assert read_stream(data, max_bytes=2 * one).num_rows == 600
    with pytest.raises(FieldError) as err:
        read_stream(data, max_bytes=2 * one - 1)
    assert err.value.field == "bytes"


def test_headers_and_plain_streams(dump_given):
    batch = request_batch(dump_given, 30)
    header = messages(stream([batch]))[1].header
    assert header.rows == 30 and header.codec is None
    assert len(header.nodes) == 8   # 5 columns, 3 of them lists with a child
    assert len(header.buffers) == len(buffer_roles(batch.schema)) == 14
    assert plain_stream(stream([batch])) and not plain_stream(stream([batch], "lz4"))
    assert not plain_stream(b"\xff\xff\xff\xff\x10\x00\x00\x00" + bytes(16))
    for bad in (b"", bytes(3), b"\x04\x00\x00\x00\xff\xff\xff\x7f", np.arange(8).tobytes()):
        with pytest.raises(ValueError):
            batch_header(bad)


def test_mutated_2d_streams_are_never_a_5xx(client_2d, coco_pair):
    """Seeded mutations (`tests.arrow_mutator.mutate`) of valid 2-D batches (every column
    variant and codec, two record batches) to the 2-D profile, answered in Arrow or JSON: a
    4xx with a field path, or a 200 whose stream validates in full; never a 5xx or a crash."""
    records = [r for r in coco_pair[0] if r["image_id"] <= 12]
    bases = []
    for variant in range(3):
        batch = request_batch_2d(records, variant=variant)
        bases += [(stream([batch.slice(0, 7), batch.slice(7)], codec), batch.schema)
                  for codec in COMPRESSIONS]
    rng = np.random.default_rng(25)
    seen: dict[int, int] = {}
    for k in range(240):
        data, schema = bases[int(rng.integers(len(bases)))]
        bad, what = mutate(data, schema, rng)
        accept = ARROW_STREAM if k % 2 else "application/json"
        r = client_2d.post(CAL + "?profile=cam2d", content=bad,
                           headers={**ARROW, "accept": accept})
        seen[r.status_code] = seen.get(r.status_code, 0) + 1
        assert r.status_code < 500, f"case {k} ({what}): {r.status_code} {r.text[:300]}"
        if r.status_code != 200:
            assert r.json()["detail"], f"case {k} ({what})"
        elif accept == ARROW_STREAM:
            with pa.ipc.open_stream(r.content) as reader:
                for out in reader:
                    out.validate(full=True)
        else:
            assert r.json()["kind"] == "boxes2d"
    assert seen.get(200) and seen.get(422), seen   # both outcomes were reached
