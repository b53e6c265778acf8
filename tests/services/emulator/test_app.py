"""The app: PyTorch kept out of the process, health, readiness and metrics, CORS for the dashboard."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from fastapi.testclient import TestClient

from services.emulator.app import create_app
from services.emulator.settings import Settings


def test_service_does_not_import_torch() -> None:
    code = (
        "import sys\n"
        "from services.emulator.app import create_app\n"
        "from services.emulator.settings import Settings\n"
        "create_app(Settings(artifacts_dir='artifacts'))\n"
        "import services.emulator.__main__\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_health_ready_metrics(client: TestClient, tmp_path: Path) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").status_code == 200
    text = client.get("/metrics").text
    assert "emulator_step_latency_seconds" in text and "emulator_batch_size" in text
    with TestClient(create_app(Settings(artifacts_dir=tmp_path))) as empty:
        assert empty.get("/healthz").status_code == 200
        assert empty.get("/readyz").status_code == 503


def test_cors_for_the_dashboard(make_client: Callable[..., TestClient]) -> None:
    client = make_client(cors_origins="http://127.0.0.1:8080")
    pre = client.options(
        "/sessions",
        headers={"Origin": "http://127.0.0.1:8080", "Access-Control-Request-Method": "POST"},
    )
    assert pre.status_code == 200
    assert pre.headers["access-control-allow-origin"] == "http://127.0.0.1:8080"
    r = client.get("/models", headers={"Origin": "http://127.0.0.1:8080"})
    assert r.headers["access-control-allow-origin"] == "http://127.0.0.1:8080"
    other = client.get("/models", headers={"Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    plain = make_client().get("/models", headers={"Origin": "http://127.0.0.1:8080"})
    assert "access-control-allow-origin" not in plain.headers


def test_a_models_forces_say_what_they_apply_and_in_what_unit(make_client: Callable[..., TestClient]) -> None:
    root = Path(__file__).resolve().parents[3] / "artifacts"  # the committed pendulum-force
    client = make_client(artifacts_dir=root)
    forces = client.get("/models/pendulum-force").json()["forces"]
    assert len(forces) == 3
    for f in forces:
        assert f["unit"] == "N" and f["component"] == 0 and f["body"], f
        assert f["description"].startswith("a push along the world x axis on ") and "in N" in f["description"]
