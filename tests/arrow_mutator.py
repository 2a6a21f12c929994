"""Hostile Arrow IPC streams for the binary calibrate path: valid request streams built from a
dump (as tests/app/calibrate/test_arrow.py builds them) or from 2-D COCO results, a seeded
mutator that corrupts them where Arrow readers trust the writer (offsets, buffer offsets and
lengths, field-node and row counts, dictionary indices, compression length prefixes, codec
bytes, raw bytes, truncation), and the issue-25 bombs and 500s.

Positions come from the stream's own framing: each message is `0xFFFFFFFF`, an int32
metadata length, the flatbuffer metadata, then the body; `calibrators.io.arrow_headers` gives
where the batch header's fields lie inside the metadata.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from calibrators.io.arrow_headers import batch_header

COMPRESSIONS = (None, "zstd", "lz4")
#: Values written over an int32 / int64 field: the segfault's offset, edges, sign flips.
HOSTILE = (0x7FFFF000, -1, 0, 1, 7, 8, 2**31 - 1, -(2**31), 2**20, 2**40, -(2**40), 16_000)


@dataclass(frozen=True)
class Message:
    """One framed message of a stream: where its metadata and body lie, and its header."""

    kind: str
    meta_at: int
    body_at: int
    body_len: int
    header: object | None    # BatchHeader of a (dictionary) batch


def _fixed(values: np.ndarray) -> pa.Array:
    flat = np.asarray(values, dtype=np.float64)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[-1])


def request_batch(dump, n: int, *, variant: int = 0) -> pa.RecordBatch:
    """A valid request batch of `n` detections of `dump`; `variant` picks the column types
    (0 fixed lists, 1 variable lists and a label column, 2 score + dictionary label, 3 large
    strings and int ids as strings)."""
    rows = np.arange(n) % len(dump.det_logits)   # the dump's detections, repeated
    logits = dump.det_logits[rows, -1].astype(np.float64)
    cols: dict[str, pa.Array] = {"frame_id": pa.array([f"f{i % 3}" for i in range(n)]),
                                 "id": pa.array(np.arange(n, dtype=np.int64))}
    if variant == 2:
        labels = np.argmax(logits, axis=1)
        cols["score"] = pa.array(1 / (1 + np.exp(-logits.max(axis=1))))
        cols["label"] = pa.DictionaryArray.from_arrays(
            pa.array(labels.astype(np.int32)), pa.array(list(dump.classes)))
    elif variant == 1:
        cols["logits"] = pa.array(logits.tolist(), pa.list_(pa.float64()))
        cols["label"] = pa.array([dump.classes[i] for i in np.argmax(logits, axis=1)])
    else:
        cols["logits"] = _fixed(logits)
    if variant == 3:
        cols["frame_id"] = pa.array([f"frame-{i % 5}" for i in range(n)], pa.large_string())
        cols["id"] = pa.array([str(i) for i in range(n)])
    box = dump.det_boxes[rows, -1]
    cols["box"] = (pa.array(box.tolist(), pa.list_(pa.float32())) if variant == 1
                   else _fixed(box))
    cols["covariance"] = _fixed(dump.det_cov[rows].reshape(n, -1))
    return pa.RecordBatch.from_pydict(cols)


def request_batch_2d(records: list[dict], *, variant: int = 0) -> pa.RecordBatch:
    """A valid 2-D request batch (`calibrators.io.arrow_boxes2d`) of COCO results `records`
    (with `layer_boxes`, as `synthetic_coco` writes them), `id` "d<i>" for record i;
    `variant` picks the column types (0 fixed lists, int64 ids, image sizes; 1 variable lists,
    narrow ints and float32, no sizes; 2 large-string ids, lists of fixed lists, float
    sizes and `logits` [2])."""
    n = len(records)
    bbox = np.asarray([r["bbox"] for r in records], dtype=np.float64).reshape(n, 4)
    layers = [r["layer_boxes"] for r in records]
    cols: dict[str, pa.Array] = {
        "image_id": pa.array([r["image_id"] for r in records],
                             pa.int32() if variant == 1 else pa.int64()),
        "id": pa.array([f"d{i}" for i in range(n)],
                       pa.large_string() if variant == 2 else pa.string()),
        "category_id": pa.array([r["category_id"] for r in records],
                                pa.int16() if variant == 1 else pa.int64())}
    if variant == 1:
        cols["bbox"] = pa.array(bbox.tolist(), pa.list_(pa.float32()))
        cols["score"] = pa.array([r["score"] for r in records], pa.float32())
        cols["layer_boxes"] = pa.array(layers, pa.list_(pa.list_(pa.float64())))
        return pa.RecordBatch.from_pydict(cols)
    cols["bbox"] = _fixed(bbox)
    cols["score"] = pa.array([r["score"] for r in records], pa.float64())
    cols["layer_boxes"] = pa.array(layers, pa.list_(pa.list_(pa.float64(), 4)))
    size = pa.float64() if variant == 2 else pa.int32()
    cols["width"], cols["height"] = pa.array([640] * n, size), pa.array([480] * n, size)
    if variant == 2:
        cols["logits"] = _fixed(np.tile([-1.0, -2.0], (n, 1)))
    return pa.RecordBatch.from_pydict(cols)


def stream(batches: list[pa.RecordBatch], compression: str | None = None) -> bytes:
    """`batches` as one IPC stream, its buffers compressed with `compression`."""
    sink = pa.BufferOutputStream()
    options = pa.ipc.IpcWriteOptions(compression=compression)
    with pa.ipc.new_stream(sink, batches[0].schema, options=options) as writer:
        for b in batches:
            writer.write_batch(b)
    return sink.getvalue().to_pybytes()


def messages(data: bytes) -> list[Message]:
    """The framed messages of a valid stream, in order (end-of-stream marker excluded)."""
    out, pos = [], 0
    for m in pa.ipc.MessageReader.open_stream(pa.BufferReader(data)):
        cont, meta_len = struct.unpack_from("<Ii", data, pos)
        assert cont == 0xFFFFFFFF, "legacy framing"
        meta_at = pos + 8
        body_len = 0 if m.body is None else m.body.size
        header = batch_header(m.metadata) if m.type in ("record batch", "dictionary") else None
        out.append(Message(m.type, meta_at, meta_at + meta_len, body_len, header))
        pos = meta_at + meta_len + body_len
    return out


def buffer_roles(schema: pa.Schema) -> list[tuple[str, str]]:
    """(column, role) of every buffer of a record batch of `schema`, in IPC order; roles:
    validity, offsets, data, indices."""
    roles: list[tuple[str, str]] = []

    def walk(name: str, kind: pa.DataType) -> None:
        roles.append((name, "validity"))
        if pa.types.is_dictionary(kind):
            roles.append((name, "indices"))
        elif pa.types.is_string(kind) or pa.types.is_large_string(kind):
            roles.extend([(name, "offsets"), (name, "data")])
        elif pa.types.is_list(kind) or pa.types.is_large_list(kind):
            roles.append((name, "offsets"))
            walk(name, kind.value_type)
        elif pa.types.is_fixed_size_list(kind):
            walk(name, kind.value_type)
        else:
            roles.append((name, "data"))

    for field in schema:
        walk(field.name, field.type)
    return roles


def mutate(data: bytes, schema: pa.Schema, rng: np.random.Generator) -> tuple[bytes, str]:
    """One corrupted copy of the valid stream `data` (of `schema`) and what was done."""
    out = bytearray(data)
    msgs = [m for m in messages(data) if m.header is not None]
    roles = buffer_roles(schema)
    m = msgs[int(rng.integers(len(msgs)))]
    h = m.header
    op = str(rng.choice(["offsets", "buffer_length", "buffer_offset", "node", "rows",
                         "prefix", "indices", "codec", "flip", "truncate"]))
    value = int(rng.choice(HOSTILE))
    if op in ("offsets", "indices", "prefix"):
        want = {"offsets": "offsets", "indices": "indices", "prefix": None}[op]
        picks = [i for i, (_, role) in enumerate(roles[:len(h.buffers)])
                 if (want is None or role == want) and h.buffers[i][1] >= 8]
        if not picks:
            op = "flip"
        else:
            i = int(rng.choice(picks))
            offset, length = h.buffers[i]
            if op == "prefix":
                struct.pack_into("<q", out, m.body_at + offset, value)
                return bytes(out), f"prefix {roles[i][0]}[{i}]={value}"
            start = 8 if h.codec else 0   # a compressed buffer: corrupt the compressed bytes
            at = offset + start + 4 * int(rng.integers(max(1, (length - start) // 4)))
            struct.pack_into("<I", out, m.body_at + at, value & 0xFFFFFFFF)
            return bytes(out), f"{op} {roles[i][0]}[{i}]@{at}={value}"
    if op in ("buffer_length", "buffer_offset") and h.buffers:
        i = int(rng.integers(len(h.buffers)))
        at = m.meta_at + h.buffers_at + 16 * i + (8 if op == "buffer_length" else 0)
        struct.pack_into("<q", out, at, value)
        return bytes(out), f"{op} {roles[i][0] if i < len(roles) else i}[{i}]={value}"
    if op == "node" and h.nodes:
        i = int(rng.integers(len(h.nodes)))
        struct.pack_into("<q", out, m.meta_at + h.nodes_at + 16 * i + 8 * int(rng.integers(2)),
                         value)
        return bytes(out), f"node {i}={value}"
    if op == "rows" and h.rows_at:
        struct.pack_into("<q", out, m.meta_at + h.rows_at, value)
        return bytes(out), f"rows={value}"
    if op == "codec":
        at = m.meta_at + int(rng.integers(m.body_at - m.meta_at))
        out[at] = int(rng.integers(256))
        return bytes(out), f"metadata byte {at}"
    if op == "truncate":
        cut = int(rng.integers(1, len(data)))
        return bytes(out[:cut]), f"truncate {cut}"
    for _ in range(int(rng.integers(1, 9))):
        at = int(rng.integers(len(out)))
        out[at] ^= 1 << int(rng.integers(8))
    return bytes(out), "flip"
