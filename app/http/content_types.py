"""Content negotiation of the calibrate routes: the body's media type (415 otherwise) and the
`Accept` header (406 when it refuses every media type a route answers a body with: an Arrow
body is answered in Arrow, or in JSON by a 2-D profile when `Accept` takes only JSON)."""

from __future__ import annotations

from fastapi import HTTPException, Request, status


def media_type(value: str) -> str:
    """The media type of a `Content-Type` or `Accept` entry, lower case, parameters dropped."""
    return value.split(";", 1)[0].strip().lower()


def body_media(request: Request, *others: str) -> str:
    """`application/json` (also any `+json` type) or one of `others`; 415 naming the
    Content-Type otherwise."""
    return content_media(request.headers.get("content-type", ""), *others)


def content_media(ctype: str, *others: str) -> str:
    """`body_media` of a `Content-Type` header value."""
    media = media_type(ctype)
    if media == "application/json" or media.endswith("+json"):
        return "application/json"
    if media in others:
        return media
    allowed = " or ".join(["application/json", *others])
    raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
                        f"Content-Type must be {allowed}, got {ctype or 'none'!r}")


def accept(request: Request, media: str, *also: str) -> None:
    """Refuse (406) a request whose `Accept` header excludes `media`, the type its body's
    format is answered in, and every type of `also` (what some profiles answer it in
    instead); no header, `*/*` and `type/*` accept it."""
    check_accept(request.headers.get("accept", ""), media, *also)


def accepts(header: str, media: str) -> bool:
    """Whether an `Accept` header value takes `media` (an empty header takes anything)."""
    if not header.strip():
        return True
    wanted = [media_type(part) for part in header.split(",")]
    kind = media.split("/", 1)[0]
    return any(w in (media, "*/*", f"{kind}/*") for w in wanted)


def check_accept(header: str, media: str, *also: str) -> None:
    """`accept` of an `Accept` header value."""
    if not any(accepts(header, m) for m in (media, *also)):
        raise HTTPException(status.HTTP_406_NOT_ACCEPTABLE,
                            f"this body is answered as {media}, which Accept {header!r} "
                            f"refuses: send the body as the format you want back")
