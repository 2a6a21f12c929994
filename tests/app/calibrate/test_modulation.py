"""A profile with logits modulation is served from every decoder layer's logits."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from app.main import create_app
from app.store import Store
from calibrators.fit import fit_profile


def test_modulated_profile_needs_and_uses_layer_logits(settings, dump_given):
    profile = fit_profile(dump_given, cov_source="given", modulation=True)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("mod", profile.to_json())
    store.close()
    idx = np.arange(12)
    dets = [{"id": int(i), "layer_logits": dump_given.det_logits[i].tolist(),
             "box": dump_given.det_boxes[i, -1].tolist(),
             "covariance": dump_given.det_cov[i].tolist()} for i in idx]
    with TestClient(create_app(settings)) as client:
        r = client.post("/v1/calibrate", json={"profile": "mod",
                                               "frames": [{"frame_id": "f", "detections": dets}]})
        assert r.status_code == 200, r.text
        got = [d["score"] for d in r.json()["frames"][0]["detections"]]
        want = profile.calibrate(layer_logits=dump_given.det_logits[idx],
                                 boxes=dump_given.det_boxes[idx, -1],
                                 covariances=dump_given.det_cov[idx]).scores
        np.testing.assert_allclose(got, want, rtol=1e-12)

        final_only = [{**d, "logits": d["layer_logits"][-1]} for d in dets[:1]]
        del final_only[0]["layer_logits"]
        r = client.post("/v1/calibrate", json={"profile": "mod",
                                               "frames": [{"frame_id": "f",
                                                           "detections": final_only}]})
        assert r.status_code == 422
        assert "layer_logits with at least 2 layers" in r.text
