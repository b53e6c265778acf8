"""Shared fixtures: small user MJCF files, emulators with random weights, tiny trained artifacts."""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainConfig
from services.stack import RedisUnavailable, find_redis
from tests.helpers import ARM_XML, Trained


def pytest_configure(config: pytest.Config) -> None:
    """Every service and command started by a test reads and writes a data directory of this test
    session, empty at first: never the user's own (``~/.local/share/neuroanimator``), and the
    committed defaults are only read."""
    os.environ[registry.DATA_DIR_ENV] = tempfile.mkdtemp(prefix="neuroanimator-test-data-")
    os.environ.pop("DATA_DIR", None)


def pytest_unconfigure(config: pytest.Config) -> None:
    shutil.rmtree(os.environ.pop(registry.DATA_DIR_ENV, ""), ignore_errors=True)


@pytest.fixture(autouse=True)
def _own_data_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test its own empty data directory: what one test trains or uploads with the defaults (``neuro
    train`` without ``--out``, a service without ``DATA_DIR``) is never another test's registry."""
    monkeypatch.setenv(registry.DATA_DIR_ENV, str(tmp_path_factory.mktemp("data")))


@pytest.fixture(autouse=True)
def _one_torch_thread() -> None:
    """Tiny networks: one intra-op thread is fastest and immune to a busy machine (the CLI sets 2)."""
    torch.set_num_threads(1)


@pytest.fixture
def arm_path(tmp_path: Path) -> Path:
    """A two-hinge arm with two limited motors, written as a user's MJCF file."""
    path = tmp_path / "arm_file.xml"
    path.write_text(ARM_XML)
    return path


@pytest.fixture
def make_emulator() -> Callable[..., StructuredEmulator]:
    """Factory: the structured emulator of a model with random core weights and random T^σ statistics."""

    def make(
        model: PhysicalModel, seed: int = 0, mode: str = "group", frame: str = "auto"
    ) -> StructuredEmulator:
        torch.manual_seed(seed)
        emu = training.build_emulator(model, TrainConfig(hidden=(16,), progress=False, frame=frame))
        gen = torch.Generator().manual_seed(seed)
        x = torch.randn(64, emu.input_size, generator=gen) * 2.0 + 0.5
        y = torch.randn(64, model.state_size, generator=gen) * 0.3 + 0.1
        emu.set_normalization(x, y, mode)
        return emu.eval()

    return make


def _train_and_save(root: Path, name: str, substeps: int) -> Trained:
    model = catalog.get(name)
    cfg = TrainConfig(
        substeps=substeps,
        examples=300,
        test_examples=100,
        hidden=(16,),
        max_epochs=20,
        progress=False,
        threads=1,
    )
    result = training.train(model, cfg)
    return Trained(model, result, artifacts.save(root, model, result), root)


@pytest.fixture(scope="session")
def artifact_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("artifacts")


@pytest.fixture(scope="session")
def trained_pendulum(artifact_root: Path) -> Trained:
    """A tiny pendulum-active emulator (n = 10), saved once for the whole session."""
    return _train_and_save(artifact_root, "pendulum-active", 10)


@pytest.fixture(scope="session")
def trained_lander(artifact_root: Path) -> Trained:
    """A tiny lander emulator (n = 10), saved once for the whole session."""
    return _train_and_save(artifact_root, "lander", 10)


def realistic_inputs(
    model: PhysicalModel, batch: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Typical states (B,S) with controls (B,U) and forces (B,F) (None where the model has none)."""
    rng = np.random.default_rng(seed)
    s = model.initial_states(rng, batch)
    times = np.zeros(1)
    u = model.typical_controls(rng, batch, times)[:, 0] if model.num_controls else None
    f = model.typical_forces(rng, batch, times)[:, 0] if model.num_forces else None
    return s, u, f


@pytest.fixture
def inputs_of() -> Callable[..., tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]:
    return realistic_inputs


# ---------------------------------------------------------------- emulator service (tests/services/emulator)
@pytest.fixture(scope="session")
def service_root(trained_pendulum: Trained, trained_lander: Trained) -> Path:
    """A registry with pendulum-active and lander (tiny, n = 10). Tests must not write to it."""
    assert trained_lander.root == trained_pendulum.root
    return trained_pendulum.root


@pytest.fixture
def make_settings(service_root: Path) -> Callable[..., Any]:
    """Factory: emulator service ``Settings`` over ``service_root`` with overrides."""
    from services.emulator.settings import Settings

    def make(**kw: Any) -> Settings:
        base: dict[str, Any] = {
            "artifacts_dir": service_root,
            "max_wait_ms": 1.0,
            "registry_poll_s": 0.0,
            "redis_url": "",  # the environment's REDIS_URL / API_KEYS must not leak into tests
            "api_keys": "",
            "api_key_secret": "test-secret",  # one for every app of a test: restored owners are kept
        }
        return Settings(**{**base, **kw})

    return make


@pytest.fixture
def make_client(make_settings: Callable[..., Any]) -> Iterator[Callable[..., Any]]:
    """Factory: a ``TestClient`` (lifespan running) over a fresh emulator app with these overrides."""
    from fastapi.testclient import TestClient

    from services.emulator.app import create_app

    clients: list[TestClient] = []

    def make(**kw: Any) -> TestClient:
        c = TestClient(create_app(make_settings(**kw)))
        c.__enter__()
        clients.append(c)
        return c

    yield make
    for c in clients:
        c.__exit__(None, None, None)


@pytest.fixture
def client(make_client: Callable[..., Any]) -> Any:
    """A ``TestClient`` over the emulator service with default test settings."""
    return make_client()


@pytest.fixture
def diverging_state(client: Any, monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """A pendulum-active state that ``client``'s emulator steps to NaN (a row that "blows up"): a session
    started there diverges at its first step; the other rows of its batch are stepped as usual."""
    from tests.helpers import service_of

    emulator = service_of(client).registry.get("pendulum-active").emulator
    real = emulator.step
    marker = 3.0

    def poisoned(state: np.ndarray, *args: Any, **kw: Any) -> np.ndarray:
        out = real(state, *args, **kw)
        out[state[:, 0] == marker] = np.nan
        return out

    monkeypatch.setattr(emulator, "step", poisoned)
    return [marker, 0.0, 0.0, 0.0, 0.0, 0.0]


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real Redis: REDIS_URL, else one on 127.0.0.1:6379, else a ``redis-server`` started on a free
    port for this test session (all by ``scripts/redis.sh``, which ``make up`` uses too)."""
    pidfile = tmp_path_factory.mktemp("redis") / "redis.pid"
    try:
        url, started = find_redis(pidfile, timeout=30)
    except RedisUnavailable as e:
        pytest.skip(f"no Redis reachable and none could be started: {e}")
    yield url
    if started is not None:
        os.kill(started, signal.SIGTERM)


@pytest.fixture
def redis_prefix(redis_url: str) -> Iterator[str]:
    """A key prefix of this test alone; its keys are removed afterwards."""
    import uuid

    import redis

    prefix = f"test-neuroanimator:{uuid.uuid4().hex[:12]}"
    yield prefix
    client = redis.Redis.from_url(redis_url)
    keys = list(client.scan_iter(match=f"{prefix}:*"))
    if keys:
        client.delete(*keys)
    client.close()
