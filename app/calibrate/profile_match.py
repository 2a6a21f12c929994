"""Does a detect request fit the profile that serves it? Its sensor is compared with the
profile's name: a profile of another sensor is served with a warning saying so (a calibrate
request's class list is checked in `app.calibrate.documents.check_classes`)."""

from __future__ import annotations

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


