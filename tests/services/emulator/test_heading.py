"""A ``heading`` is reported wrapped to [-π, π): the truck turning circles through the service's step,
its frames and its MuJoCo shadow (the committed truck emulator), turning past π."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from neuroanimator.core.state import heading_columns
from services.emulator.app import create_app
from services.emulator.scene import MujocoShadow
from services.emulator.settings import Settings

ROOT = Path(__file__).resolve().parents[3]


def test_truck_heading_is_wrapped_in_steps_and_frames() -> None:
    app = create_app(
        Settings(artifacts_dir=ROOT / "artifacts", registry_poll_s=0.0, redis_url="", api_keys="")
    )
    with TestClient(app) as client:
        start = [0.0, 0.0, 3.0, 0.0, 0.0, 0.0]  # at rest, facing nearly -x
        sid = client.post("/sessions", json={"model": "truck", "state": start}).json()["id"]
        # full gas and full left steering: it turns counter-clockwise, the heading grows past π
        r = client.post(
            f"/sessions/{sid}/step", json={"controls": [10.0, 5.0], "steps": 40, "frames_per_step": 5}
        )
        assert r.status_code == 200, r.text
        body = r.json()
    detail_layout = app.state.service.registry.get("truck", None).manifest.layout
    (col,) = heading_columns(detail_layout)
    headings = np.array([s[col] for s in body["states"]])
    frames = np.array([f[col] for f in body["frames"]])
    assert np.all(np.abs(headings) <= np.pi + 1e-6) and np.all(np.abs(frames) <= np.pi + 1e-6)  # float32
    assert np.unwrap(np.r_[3.0, headings])[-1] > np.pi + 1.0, "it turned well past π"
    assert np.max(np.abs(np.diff(np.unwrap(frames)))) < 1.0  # no frame spins through zero


def test_the_mujoco_shadow_reports_its_heading_wrapped() -> None:
    from neuroanimator import catalog

    truck = catalog.get("truck")
    twin = MujocoShadow(truck, 50, np.array([0.0, 0.0, 3.0, 0.0, 0.0, 0.0]))
    seen = [twin.step(np.array([10.0, 5.0], np.float32), np.zeros(0, np.float32))[2] for _ in range(40)]
    assert all(-np.pi <= h < np.pi for h in seen)
    assert np.unwrap(np.r_[3.0, seen])[-1] > np.pi + 1.0
