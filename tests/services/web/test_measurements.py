"""The dashboard's server answers each model's evaluation and benchmark, put together from the results
stored in its current versions, and each version's own."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from neuroanimator.artifacts import registry
from neuroanimator.core.results import ModelBench, ModelEval, VersionBench, VersionEval
from services.web.app import create_app
from services.web.settings import Settings

ARTIFACTS = Path(__file__).resolve().parents[3] / "artifacts"


@pytest.fixture
def root(tmp_path: Path) -> Path:
    for model in ("lander", "truck"):
        shutil.copytree(ARTIFACTS / model, tmp_path / model)
    return tmp_path


@pytest.fixture
def client(root: Path) -> TestClient:
    return TestClient(create_app(Settings(artifacts_dir=root, web_dist=root / "no-dist")))


def test_model_results_over_its_versions(client: TestClient) -> None:
    r = client.get("/artifacts/lander/eval.json")
    assert r.status_code == 200 and r.headers["cache-control"] == "no-cache"
    ev = ModelEval.model_validate(r.json())
    assert [row.substeps for row in ev.by_substeps] == [25, 50, 100] and ev.substeps == 50
    assert ev.rollout_error_curve.t[0] == 0.0 and ev.n100_vs_n25_at_20s is not None
    bench = ModelBench.model_validate(client.get("/artifacts/lander/bench.json").json())
    assert [row.substeps for row in bench.single] == [25, 50, 100] and bench.batched_substeps == 50


def test_one_versions_results(client: TestClient, root: Path) -> None:
    version = registry.latest_version(root, "truck", 100)
    ev = VersionEval.model_validate(client.get(f"/artifacts/truck/{version}/eval.json").json())
    assert (ev.version, ev.substeps) == (version, 100)
    bench = VersionBench.model_validate(client.get(f"/artifacts/truck/{version}/bench.json").json())
    assert bench.single is not None and bench.batched == []  # batched at n = 50 only


def test_what_was_not_measured_is_404(client: TestClient, root: Path) -> None:
    for n in (25, 50, 100):
        (registry.resolve(root, "truck", substeps=n) / registry.EVAL_FILE).unlink()
    for url in (
        "/artifacts/truck/eval.json",
        f"/artifacts/truck/{registry.latest_version(root, 'truck')}/eval.json",
        "/artifacts/submarine/eval.json",
        "/artifacts/truck/n1-nope/bench.json",
        "/artifacts/truck/manifest.json",
        "/artifacts/..%2Ftruck/eval.json",
    ):
        r = client.get(url)
        assert r.status_code == 404, url
        assert r.json()["error"] == "not_measured"


def test_an_unreadable_result_is_500_without_details(client: TestClient, root: Path) -> None:
    (registry.resolve(root, "lander") / registry.BENCH_FILE).write_text("{broken")
    r = client.get("/artifacts/lander/bench.json")
    assert r.status_code == 500 and r.json()["error"] == "unreadable"
    assert str(root) not in r.text


def test_an_uploaded_models_results_are_hidden_while_it_is_private_with_keys_on(root: Path) -> None:
    """The dashboard's server takes no key: with keys on, an uploaded model's results are answered only
    once an operator published it (for the others it does not exist, as in every service)."""
    from services.common import tenancy

    tenancy.write(root, "truck", tenancy.Ownership.new("some-key-id"))
    version = registry.latest_version(root, "truck", 50)
    keys_on = TestClient(create_app(Settings(artifacts_dir=root, web_dist=root / "no-dist", api_keys="k1")))
    keys_off = TestClient(create_app(Settings(artifacts_dir=root, web_dist=root / "no-dist", api_keys="")))
    for path in ("/artifacts/truck/eval.json", f"/artifacts/truck/{version}/bench.json"):
        hidden = keys_on.get(path)
        assert hidden.status_code == 404 and hidden.json()["error"] == "not_measured"
        assert keys_off.get(path).status_code == 200
    assert keys_on.get("/artifacts/lander/eval.json").status_code == 200  # not uploaded: everybody's
    tenancy.write(root, "truck", tenancy.Ownership("some-key-id", published=True))
    assert keys_on.get("/artifacts/truck/eval.json").status_code == 200


def test_a_model_lists_the_measurements_it_has(client: TestClient, root: Path) -> None:
    """The dashboard asks only for what ``/artifacts/{model}`` lists: a model trained without a
    benchmark (an upload) lists its evaluation alone, and its page makes no request that fails."""
    r = client.get("/artifacts/lander")
    assert r.status_code == 200 and r.json() == {"model": "lander", "measured": ["eval.json", "bench.json"]}
    for n in (25, 50, 100):
        (registry.resolve(root, "truck", substeps=n) / registry.BENCH_FILE).unlink()
    assert client.get("/artifacts/truck").json()["measured"] == ["eval.json"]
    assert client.get("/artifacts/submarine").json() == {"model": "submarine", "measured": []}
