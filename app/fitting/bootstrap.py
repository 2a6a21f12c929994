"""First start: an admin token for local use and a default profile from the bundled detector.

`ensure_admin_token` writes `data_dir/admin_token` (mode 0600) when no token is configured.
`ensure_default_profile` fits the default profile when the store has none, from a shipped
validation dump of the bundled lidar detector (`detectors/data/lidar_val.npz`) if present,
else from one generated on the spot by the detectors package (a few dozen simulated
validation frames). The dump is kept content-addressed in the store, like an upload.
"""

from __future__ import annotations

import io
import os
import secrets
import time
from collections.abc import Callable
from pathlib import Path

from app.settings import TOKEN_FILE, Settings
from app.store import ProfileRecord, Store

BOOTSTRAP_FRAMES = 60
Say = Callable[[str], None]


def ensure_admin_token(settings: Settings, say: Say = print) -> Path | None:
    """Generate `data_dir/admin_token` (0600) if no token is configured, and say where the
    token is on every start; its path, or None when it comes from the environment."""
    path = settings.data_dir / TOKEN_FILE
    if settings.admin_token is not None:
        if path.is_file():
            say(f"detcal: the admin token is in {path.resolve()}; use it as "
                f"'Authorization: Bearer $(cat {path.resolve()})'")
            return path
        say("detcal: the admin token is the one set in DETCAL_ADMIN_TOKEN")
        return None
    settings.data_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    say(f"detcal: generated an admin token in {path} (mode 0600); use it as "
        f"'Authorization: Bearer $(cat {path})'")
    return path


def shipped_dump(sensor: str = "lidar") -> Path | None:
    """The validation dump shipped with the detectors package, if any."""
    try:
        import detectors
    except ImportError:
        return None
    path = Path(detectors.__file__).resolve().parent / "data" / f"{sensor}_val.npz"
    return path if path.is_file() else None


def generate_dump_bytes(sensor: str = "lidar", n_frames: int = BOOTSTRAP_FRAMES,
                        say: Say = print) -> bytes:
    """An NPZ validation dump of the bundled detector on the first `n_frames` val scenes."""
    import torch

    from calibrators.io import save_dump
    from detectors import build_detector
    from detectors.dumpwriter import build_dump
    from detectors.sim import split_seeds

    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    model = build_detector(sensor)
    start = time.monotonic()

    def progress(i: int, n: int) -> None:
        if i == n or i % 10 == 0:
            say(f"detcal: {sensor} validation frames {i}/{n} "
                f"({time.monotonic() - start:.0f} s)")

    dump = build_dump(model, split_seeds("val", n_frames), progress=progress)
    buf = io.BytesIO()
    save_dump(buf, dump)
    return buf.getvalue()


BOOTSTRAP_HOLDOUT = 0.3


def ensure_default_profile(settings: Settings, say: Say = print,
                           n_frames: int = BOOTSTRAP_FRAMES) -> ProfileRecord | None:
    """Fit and store the default profile if the store holds no profile; the new version."""
    from calibrators.fit import fit_profile
    from calibrators.io import load_dump

    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    try:
        if store.count_profiles() > 0:
            return None
        shipped = shipped_dump("lidar")
        if shipped is not None:
            say(f"detcal: fitting the default profile from the shipped dump {shipped}")
            with shipped.open("rb") as f:
                stored = store.put_dump(f, "npz")
        else:
            say(f"detcal: no profile yet; generating a lidar validation dump "
                f"({n_frames} simulated frames)")
            stored = store.put_dump(io.BytesIO(generate_dump_bytes("lidar", n_frames, say)),
                                    "npz")
        dump = load_dump(store.dump_path(stored.sha256))
        # The bundled detector's covariance is the spread of a query's box across decoder
        # layers; fitting on that source lets clients send `layer_boxes` as the detector
        # emits them instead of computing a covariance themselves.
        source = "layers" if dump.n_layers >= 2 else "auto"
        # A held-out part (30 % of the frames) so the dashboard shows how the served scores
        # and ellipses hold on frames the profile never saw.
        profile = fit_profile(dump, cov_source=source, holdout=BOOTSTRAP_HOLDOUT,
                              dump_sha256=stored.sha256)
        record = store.add_profile(settings.default_profile, profile.to_json(),
                                   dump_sha256=stored.sha256, activate=True)
        say(f"detcal: stored profile {record.ref}: scores {profile.score_method}, covariance "
            f"{profile.cov_method}, regions {profile.region_method} (T = "
            f"{profile.temperature:.3f}, pooled k = {profile.pooled_k:.4g})")
        return record
    finally:
        store.close()
