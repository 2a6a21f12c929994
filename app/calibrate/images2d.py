"""The `images` of a POST /v1/calibrate request to a 2-D profile: the request's detections as
one `Detections2D` batch (each keeping its image and its row in that image's `detections`),
calibrated by `calibrators.boxes2d.calibrate_2d`, and answered per image as COCO results
records (the records `detcal calibrate` writes) with `row` and `id`.

Imported only when a request meets a 2-D profile (or sends `images`): the 3-D calibrate path
never loads it. A body of the other kind is a 422 at the field that does not fit the profile
(`frames` for a 2-D profile, `images` for a 3-D one); a library `FieldError` is a 422 at the
detection's field (`body.images[i].detections[j].bbox`). The answer document
(`document_2d`) is also the JSON answer to a 2-D Arrow body (`app.calibrate.arrow2d`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.http.errors import RequestError
from app.schemas.calibrate import CalibrateRequest
from calibrators.boxes2d import Calibrated2D, Detections2D, calibrate_2d
from calibrators.core.errors import FieldError

#: Fields of a 3-D request that a 2-D profile does not read.
_THREE_D_ONLY = ("classes", "ellipse_confidence")
_DETECTION_FIELDS = ("category_id", "bbox", "score", "logits", "layer_boxes")


def calibrate_images(loaded: LoadedProfile, body: CalibrateRequest, given: set[str],
                     max_detections: int | None) -> tuple[dict[str, Any], int]:
    """The response document of a calibrate request to a 2-D profile and how many detections
    it calibrated; `given` names the options the request set itself (body or query)."""
    ref = loaded.record.ref
    if loaded.kind == "3d":
        raise RequestError(["body", "images"], f"profile {ref} is a 3-D profile: send its "
                                               "detections as `frames`")
    if body.images is None:
        raise RequestError(["body", "frames"], f"profile {ref} is a 2-D (boxes2d) profile: "
                                               "send 2-D detections as `images` (docs/api.md)")
    for key in _THREE_D_ONLY:
        if key in given:
            raise three_d_option(key, ref, "body")
    where = [(i, j) for i, image in enumerate(body.images)
             for j in range(len(image.detections))]
    if max_detections is not None and len(where) > max_detections:
        raise RequestError(["body", "images"], f"the request carries {len(where)} detections; "
                           f"at most {max_detections} are calibrated per request "
                           f"(DETCAL_MAX_DETECTIONS): split it", status=413)
    profile = loaded.profile
    levels = body.levels if "levels" in given else None
    try:
        detections = _detections(body, where)
        size = _image_size(body, where, profile.image_size) \
            if profile.reads_image_size else None
        served = calibrate_2d(profile, detections, levels, size)
    except FieldError as exc:
        raise _located(exc, where, ref) from None
    records = served.records()
    images: list[dict[str, Any]] = [{"image_id": image.image_id, "detections": []}
                                    for image in body.images]
    for record, (i, j) in zip(records, where, strict=True):
        images[i]["detections"].append({"row": j, "id": body.images[i].detections[j].id,
                                        **record})
    return document_2d(loaded, served, images), len(records)


def profile_fields_2d(loaded: LoadedProfile) -> dict[str, Any]:
    """What a 2-D answer says of its profile: `profile` (its ref), `kind`, `categories`."""
    profile = loaded.profile
    return {"profile": loaded.ref(), "kind": loaded.kind,
            "categories": [{"id": c, "name": n} for c, n in
                           zip(profile.category_ids, profile.category_names, strict=True)]}


def document_2d(loaded: LoadedProfile, served: Calibrated2D, images: list[dict[str, Any]]
                ) -> dict[str, Any]:
    """The answer (`CalibrateResponse2D`) of `served` whose detections are grouped in
    `images` (`[{image_id, detections}]`)."""
    return {**profile_fields_2d(loaded),
            "levels": None if served.regions is None else served.regions.levels.tolist(),
            "images": images}


def three_d_option(key: str, ref: str, where: str) -> RequestError:
    """The 422 of an option of 3-D profiles (`key`, in the body or the query) sent to the
    2-D profile `ref`."""
    return RequestError([where, key], f"{key} is an option of 3-D profiles; profile {ref} is "
                                      "a 2-D (boxes2d) profile")


def _detections(body: CalibrateRequest, where: list[tuple[int, int]]) -> Detections2D:
    """The request's detections as one batch, row r being `where[r]`."""
    assert body.images is not None
    dets = [body.images[i].detections[j] for i, j in where]
    columns: dict[str, Any] = {}
    for key in ("logits", "layer_boxes"):
        given = [getattr(d, key) is not None for d in dets]
        if any(given) and not all(given):
            r = given.index(not given[0])   # the first detection unlike the first
            raise FieldError(key, f"give {key} with every detection or with none", row=r)
        if dets and all(given):
            try:
                columns[key] = np.asarray([getattr(d, key) for d in dets], dtype=np.float64)
            except ValueError:   # ragged
                width = len(getattr(dets[0], key))
                r = next(r for r, d in enumerate(dets) if len(getattr(d, key)) != width)
                raise FieldError(key, f"{key} must have the same length in every detection "
                                      f"({width}, as the first)", row=r) from None
    return Detections2D(
        image_id=np.asarray([body.images[i].image_id for i, _ in where], dtype=np.int64),
        category_id=np.asarray([d.category_id for d in dets], dtype=np.int64),
        bbox=np.asarray([d.bbox for d in dets], dtype=np.float64).reshape(len(dets), 4),
        score=np.asarray([d.score for d in dets], dtype=np.float64), **columns)


def _image_size(body: CalibrateRequest, where: list[tuple[int, int]],
                default: tuple[int, int] | None) -> np.ndarray:
    """`[N, 2]` width and height of each detection's image: the image's own, else the
    profile's `default`; FieldError naming the first image with neither."""
    assert body.images is not None
    sizes = []
    for i, image in enumerate(body.images):
        if (image.width is None) != (image.height is None):
            raise RequestError(["body", "images", i, "width" if image.width is None
                                else "height"], "give the image's width and height together")
        size = default if image.width is None else (image.width, image.height)
        if size is None:
            raise RequestError(["body", "images", i, "width"], "this profile reads where "
                               "each box lies in its image (its score calibrator or box "
                               "regions): give each image's width and height")
        sizes.append(size)
    return np.asarray([sizes[i] for i, _ in where], dtype=np.float64).reshape(len(where), 2)


def _located(exc: FieldError, where: list[tuple[int, int]], ref: str) -> RequestError:
    """The 422 of a library `FieldError` about the batch, at the detection's field."""
    field = "bbox" if exc.field == "boxes" else exc.field
    if field == "levels":
        return RequestError(["body", "levels", *([] if exc.row is None else [exc.row])],
                            str(exc))
    row = 0 if exc.row is None and field in ("logits", "layer_boxes") else exc.row
    if field in _DETECTION_FIELDS and row is not None and 0 <= row < len(where):
        i, j = where[row]   # a shape every detection shares is named at the first
        return RequestError(["body", "images", i, "detections", j, field],
                            f"profile {ref}: {_row_text(exc, i, j)}",
                            kind="value_error.profile_mismatch")
    return RequestError(["body", "images"], f"profile {ref}: {exc}",
                        kind="value_error.profile_mismatch")


def _row_text(exc: FieldError, i: int, j: int) -> str:
    """The library's message with its batch row `[r]` named as the request's detection."""
    text = str(exc)
    return text.replace(f"[{exc.row}]", f" of images[{i}].detections[{j}]", 1) \
        if f"[{exc.row}]" in text else text
