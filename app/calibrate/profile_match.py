"""Does a request fit the profile that serves it? A detect request's sensor and a calibrate
request's class list are compared with the profile: what cannot be served is a 422 naming the
field, what can but may be wrong is served with a warning saying so."""

from __future__ import annotations

from collections.abc import Sequence

from app.calibrate.cache import LoadedProfile, ProfileCache
from app.http.errors import RequestError
from app.store import NotFoundError
from detectors.vocab import SENSORS


def profile_for_sensor(cache: ProfileCache, ref: str | None, sensor: str, default: str
                       ) -> tuple[LoadedProfile, list[str]]:
    """The profile a `/v1/detect` of `sensor` is served with, and warnings: with no `ref`, the
    profile named after the sensor when there is one, else the default profile (warned: it may
    have been fit on another detector's outputs); a named profile of another sensor's name is
    served as asked, with a warning."""
    if ref is None:
        try:
            return cache.resolve(sensor, default), []
        except (NotFoundError, RequestError):   # no such profile, or not a profile name
            loaded = cache.resolve(None, default)
            if loaded.record.name == sensor:
                return loaded, []
            return loaded, [
                f"no profile is named {sensor!r}: the {sensor} detections were calibrated with "
                f"the default profile {loaded.record.ref}, fit on another detector's outputs "
                f"unless you fit it on {sensor} detections; fit one with POST /v1/fit "
                f"(name={sensor}) or name a profile in `profile`"]
    loaded = cache.resolve(ref, default)
    name = loaded.record.name
    if name != sensor and name in SENSORS:
        return loaded, [f"profile {loaded.record.ref} is named after another sensor than "
                        f"{sensor!r}: its scores and ellipses hold for {name} detections"]
    return loaded, []


def check_classes(loaded: LoadedProfile, classes: Sequence[str] | None) -> None:
    """A 422 at `body.classes` when the client's class list (its logits' column order) is not
    the profile's: the columns would be read as other classes."""
    if classes is None:
        return
    want = list(loaded.profile.classes)
    got = list(classes)
    if got == want:
        return
    missing = [c for c in want if c not in got]
    extra = [c for c in got if c not in want]
    if missing or extra:
        why = "; ".join(part for part in (
            f"missing {', '.join(missing)}" if missing else "",
            f"not in the profile: {', '.join(extra)}" if extra else "") if part)
    else:
        first = next(i for i, (a, b) in enumerate(zip(got, want, strict=True)) if a != b)
        why = (f"same classes in another order (column {first} is {got[first]!r}, the profile's "
               f"is {want[first]!r})")
    raise RequestError(["body", "classes"], f"classes do not match profile "
                                            f"{loaded.record.ref} ({', '.join(want)}): {why}")
