"""The cache of simulated training data: a second training with the same data settings reads what the
first simulated; any other setting simulates its own."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.cli import main
from neuroanimator.sim import sampling
from neuroanimator.training import data_cache
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainConfig


def _cfg(**kw: object) -> TrainConfig:
    base = dict(
        substeps=50, examples=400, test_examples=100, hidden=(8,), max_epochs=2,
        rollout_steps=0, time_budget=None, threads=1, progress=False,
    )  # fmt: skip
    return TrainConfig(**{**base, **kw})  # type: ignore[arg-type]


def test_a_second_training_reads_the_first_ones_examples(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    model = catalog.get("pendulum-active")
    first = training.train(model, _cfg(), data_cache=tmp_path)
    kept = sorted(p.name for p in tmp_path.iterdir())
    assert len(kept) == 2  # the training runs and the held-out examples
    assert [n.split("-n50-")[0] for n in kept] == ["pendulum-active-examples", "pendulum-active-sequences"]
    with caplog.at_level(logging.INFO, logger="neuroanimator.training.data_cache"):
        second = training.train(model, _cfg(lr=1e-2), data_cache=tmp_path)  # a training setting changed
    assert second.data_sha256 == first.data_sha256
    assert sum("read from" in r.message for r in caplog.records) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == kept  # nothing new, no partial file left


def test_other_data_settings_simulate_their_own(tmp_path: Path) -> None:
    model = catalog.get("pendulum-active")
    first = training.train(model, _cfg(), data_cache=tmp_path)
    other = training.train(model, _cfg(seed=5), data_cache=tmp_path)
    assert other.data_sha256 != first.data_sha256
    assert len(list(tmp_path.iterdir())) == 4
    keys = {
        data_cache.cache_key(model, n, count, seed, sampler)
        for n, count, seed, sampler in [(50, 400, 0, "runs"), (25, 400, 0, "runs"), (50, 401, 0, "runs"),
                                        (50, 400, 1, "runs"), (50, 400, 0, "spaced")]
    }  # fmt: skip
    assert len(keys) == 5
    assert data_cache.cache_key(catalog.get("lander"), 50, 400, 0, "runs") not in keys
    assert data_cache.cache_key(model, 50, 400, 0, "runs", "sequences") not in keys


def test_a_file_whose_key_differs_is_simulated_again(tmp_path: Path) -> None:
    model = catalog.get("pendulum-active")
    calls: list[int] = []

    def simulate() -> sampling.Examples:
        calls.append(1)
        return sampling.generate(model, 50, 50, 3, progress=False)

    def read() -> sampling.Examples:
        return data_cache.cached(tmp_path, model, 50, 50, 3, "runs", simulate, sampling.Examples)

    data = read()
    (path,) = tmp_path.iterdir()
    with np.load(path) as z:  # the same name over other data (a file copied in by hand)
        arrays = {k: z[k] for k in z.files}
    np.savez(path, **{**arrays, "key": np.asarray("0" * 64)})
    again = read()
    assert len(calls) == 2
    assert again.sha256() == data.sha256()
    assert read().sha256() == data.sha256()
    assert len(calls) == 2  # the rewritten file is read


def test_no_directory_means_no_cache(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(data_cache.ENV, raising=False)
    assert data_cache.directory(None) is None
    assert data_cache.directory(tmp_path) == tmp_path
    monkeypatch.setenv(data_cache.ENV, str(tmp_path / "env"))
    assert data_cache.directory(None) == tmp_path / "env"
    assert data_cache.directory(tmp_path) == tmp_path  # the option wins over the environment


def test_neuro_train_keeps_its_examples_in_the_directory_given(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    args = [
        "train", "pendulum-active", "--out", str(tmp_path / "a"), "--examples", "300", "--epochs", "2",
        "--rollout-steps", "0", "--quiet", "--force", "--data-cache", str(cache),
    ]  # fmt: skip
    assert main(args) == 0
    assert len(list(cache.glob("pendulum-active-*.npz"))) == 2
