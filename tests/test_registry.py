"""The registry's read side: finding versions (and naming what is missing), and the evaluation and
benchmark results stored per version, summarised per model."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import pytest

from neuroanimator.artifacts import registry
from neuroanimator.core.results import (
    BatchedSpeed,
    ModelBench,
    NetworkSize,
    RolloutCurve,
    SingleClientSpeed,
    VersionEval,
    split_bench,
)

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"


@pytest.fixture
def lander(tmp_path: Path) -> Path:
    """A copy of the committed lander artifacts (n = 25, 50, 100; latest n = 50), as a registry root."""
    shutil.copytree(ARTIFACTS / "lander", tmp_path / "lander")
    return tmp_path


def _eval(root: registry.Root, n: int, at_20s: float) -> VersionEval:
    version = registry.latest_version(root, "lander", n)
    t = [0.0, 10.0, 20.0, 30.0]
    return VersionEval(
        model="lander",
        version=version,
        substeps=n,
        one_step_rel_error=0.001,
        linear_baseline_rel_error=0.1,
        baseline_ratio=100.0,
        rollout_error_curve=RolloutCurve(t=t, error=[0.0, at_20s / 2, at_20s, at_20s * 2]),
        rollout_error_at_20s=at_20s,
        rollout_error_final=at_20s * 2,
        architecture=NetworkSize(hidden=[64, 64], activation="tanh", weights=5901),
    )


@pytest.mark.parametrize(
    ("model", "version", "substeps", "what", "text"),
    [
        ("submarine", None, None, "model", "unknown model 'submarine'; trained models are ['lander']"),
        ("../lander", None, None, "model", "unknown model '../lander'"),
        (
            "lander",
            None,
            7,
            "substeps",
            "model 'lander' has no emulator for substeps=7; it has [25, 50, 100]",
        ),
        ("lander", "n1-nope", None, "version", "model 'lander' has no version 'n1-nope'; it has ['n100-"),
        ("lander", "../truck/latest", None, "version", "has no version '../truck/latest'"),
        ("lander", "n100-20261121T145529", 50, "substeps", "has substeps=100, got 50"),
    ],
)
def test_resolve_names_what_is_missing(
    lander: Path, model: str, version: str | None, substeps: int | None, what: str, text: str
) -> None:
    with pytest.raises(registry.ArtifactError) as exc:
        registry.resolve(lander, model, version, substeps)
    assert exc.value.what == what
    assert text in str(exc.value)


def test_listing(lander: Path) -> None:
    (lander / "not a model").mkdir()
    (lander / "half-written").mkdir()  # no latest pointer: not listed
    assert registry.list_models(lander) == ["lander"]
    assert registry.list_models(lander / "absent") == []
    assert registry.available_substeps(lander, "lander") == [25, 50, 100]
    assert registry.versions(lander, "lander") == sorted(p.name for p in (lander / "lander").glob("n*"))
    assert registry.latest_version(lander, "lander") == registry.latest_version(lander, "lander", 50)


def test_version_names_follow_one_pattern() -> None:
    when = dt.datetime(2026, 11, 21, 14, 38, 38, tzinfo=dt.UTC)
    assert registry.version_name(50, when) == "n50-20261121T143838"
    assert registry.version_name(50, when, repeat=2) == "n50-20261121T143838-2"
    assert registry.pointer_name() == "latest" and registry.pointer_name(25) == "latest-n25"


def test_committed_results_are_stored_per_version_and_typed() -> None:
    for model in registry.list_models(ARTIFACTS):
        assert (
            not (ARTIFACTS / model / "eval.json").exists() and not (ARTIFACTS / model / "bench.json").exists()
        )
        for n in registry.available_substeps(ARTIFACTS, model):
            path = registry.resolve(ARTIFACTS, model, substeps=n)
            ev, bench = registry.read_eval(path), registry.read_bench(path)
            assert ev is not None and (ev.model, ev.version, ev.substeps) == (model, path.name, n)
            assert bench is not None and bench.single is not None and bench.single.version == path.name
        ns = registry.available_substeps(ARTIFACTS, model)  # the thesis models: 25, 50 and 100
        summary = registry.model_eval(ARTIFACTS, model)
        assert summary is not None and [r.substeps for r in summary.by_substeps] == ns
        speed = registry.model_bench(ARTIFACTS, model)
        assert speed is not None and [r.substeps for r in speed.single] == ns
        # 4,096 where MuJoCo's side fits the time: the runner's 20 s at B = 4,096 would take 40 minutes
        assert [r.batch for r in speed.batched] in ([1, 64, 1024, 4096], [1, 64, 1024]), model
        if ns == [25, 50, 100]:
            # the summary is of the version "latest" points to: the model's own super-step (the
            # quadrotor's is 25, the thesis models' 50)
            latest = registry.read_manifest(registry.resolve(ARTIFACTS, model))
            assert summary.substeps == latest.substeps and summary.n100_vs_n25_at_20s is not None
            assert speed.batched_substeps == 50


def test_results_written_per_version_are_summarised_per_model(lander: Path) -> None:
    for n in (25, 50, 100):
        (registry.resolve(lander, "lander", substeps=n) / registry.EVAL_FILE).unlink(missing_ok=True)
    assert registry.model_eval(lander, "lander") is None
    written = registry.write_eval(lander, _eval(lander, 50, 0.2))
    assert written.parent == registry.resolve(lander, "lander", substeps=50)
    assert registry.read_eval(written.parent) == _eval(lander, 50, 0.2)
    one = registry.model_eval(lander, "lander")
    assert one is not None and [r.substeps for r in one.by_substeps] == [50]
    assert one.n100_vs_n25_at_20s is None and one.thesis_preset.hidden == [50]
    registry.write_eval(lander, _eval(lander, 25, 0.2))
    registry.write_eval(lander, _eval(lander, 100, 0.3))
    three = registry.model_eval(lander, "lander")
    assert three is not None and [r.substeps for r in three.by_substeps] == [25, 50, 100]
    assert three.version == registry.latest_version(lander, "lander")  # the primary row is latest's
    assert three.n100_vs_n25_at_20s == pytest.approx(1.5)
    assert three.plot == "lander/rollout_error.png"


def test_a_model_benchmark_splits_into_versions_and_back(lander: Path) -> None:
    versions = {n: registry.latest_version(lander, "lander", n) for n in (25, 50, 100)}
    bench = ModelBench(
        model="lander",
        single=[
            SingleClientSpeed(substeps=n, version=v, physics_s=1.0, emulator_s=0.1, ratio=10.0)
            for n, v in versions.items()
        ],
        batched=[BatchedSpeed(batch=64, physics_steps_per_s=1e5, emulator_steps_per_s=1e7, ratio=100.0)],
        batched_substeps=50,
        batched_version=versions[50],
    )
    records = split_bench(bench)
    assert [(r.substeps, len(r.batched)) for r in records] == [(25, 0), (50, 1), (100, 0)]
    for r in records:
        registry.write_bench(lander, r)
    assert registry.model_bench(lander, "lander") == bench


def test_an_unreadable_result_names_its_file(lander: Path) -> None:
    path = registry.resolve(lander, "lander")
    (path / registry.BENCH_FILE).write_text('{"model": "lander"}')
    with pytest.raises(registry.ArtifactError, match=r"bench\.json") as exc:
        registry.read_bench(path)
    assert exc.value.what == "results"


def test_the_data_directory_is_read_over_the_committed_defaults(lander: Path, tmp_path: Path) -> None:
    """Uploads and a user's trainings live in a data directory of their own; a service reads it first,
    then the committed defaults, as one registry."""
    data = tmp_path / "data"
    data.mkdir()
    roots = registry.Roots(data, lander)
    assert registry.list_models(roots) == ["lander"] and roots.read_only_has("lander")
    shutil.copytree(lander / "lander", data / "mine")  # a user's model: listed beside the defaults
    assert registry.list_models(roots) == ["lander", "mine"] and not roots.read_only_has("mine")
    assert registry.resolve(roots, "mine").parent == data / "mine"
    assert registry.list_models(lander) == ["lander"]  # the defaults alone are what they were
    (data / "lander").mkdir()  # half written (no latest yet): it does not hide the default
    assert registry.resolve(roots, "lander").parent == lander / "lander"
    assert registry.list_models(roots) == ["lander", "mine"]
    shutil.copytree(lander / "lander", data / "lander", dirs_exist_ok=True)  # a user's own training of it
    assert registry.resolve(roots, "lander").parent == data / "lander"
    assert registry.available_substeps(roots, "lander") == [25, 50, 100]
    with pytest.raises(registry.ArtifactError, match=r"trained models are \['lander', 'mine'\]"):
        registry.resolve(roots, "submarine")
    assert roots / "new" == data / "new"  # a new model is written to the data directory
    written = registry.write_eval(roots, _eval(roots, 25, 0.01))  # results go beside their version
    assert written.is_relative_to(data / "lander")


def test_a_version_no_pointer_names_is_found_by_name_in_any_registry(lander: Path, tmp_path: Path) -> None:
    """A committed model's emulator fine-tuned for a policy is written to the data directory without a
    pointer: resolved by its name there and listed among the model's versions, while the model's
    pointers stay the defaults'."""
    data = tmp_path / "data"
    roots = registry.Roots(data, lander)
    base = registry.resolve(roots, "lander", substeps=25)
    tuned = f"{base.name}-tuned-20261205T120000"
    shutil.copytree(base, data / "lander" / tuned)
    assert registry.resolve(roots, "lander", tuned) == data / "lander" / tuned
    assert registry.version_folder(roots, "lander", tuned) == data / "lander" / tuned
    assert registry.resolve(roots, "lander").parent == lander / "lander"  # the pointers are the defaults'
    listed = registry.versions(roots, "lander")
    assert tuned in listed and set(registry.versions(lander, "lander")) < set(listed)
    assert registry.model_size(roots, "lander") > registry.model_size(lander, "lander")
    assert registry.version_folder(roots, "lander", "../lander/" + tuned) is None  # a name, never a path
    assert registry.version_folder(roots, "lander", "n25-nope") is None
    (data / "lander" / "n25-half").mkdir()  # no manifest: not a version
    with pytest.raises(registry.ArtifactError, match="has no version 'n25-half'"):
        registry.resolve(roots, "lander", "n25-half")


def test_the_default_data_directory_is_outside_the_source_tree(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(registry.DATA_DIR_ENV, str(tmp_path / "mine"))
    assert registry.default_data_dir() == tmp_path / "mine"
    monkeypatch.delenv(registry.DATA_DIR_ENV)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert registry.default_data_dir() == tmp_path / "xdg" / "neuroanimator"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert registry.default_data_dir() == tmp_path / "home" / ".local" / "share" / "neuroanimator"
    assert registry.DEFAULTS_DIR == ARTIFACTS
    assert registry.Roots.default().folders == (tmp_path / "home/.local/share/neuroanimator", ARTIFACTS)
