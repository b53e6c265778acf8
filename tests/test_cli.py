"""The ``neuro`` command line: train, eval, bench, models, and how it reports bad input."""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.cli import CONFIG_OPTIONS, build_parser, given_fields, main
from neuroanimator.core.results import ModelBench, ModelEval
from neuroanimator.core.train_config import TrainConfig
from tests.helpers import ARM_XML, Trained


@dataclass
class CliRun:
    rc: int
    stdout: str
    root: Path


# the smallest training that still runs every phase of ``--substeps auto`` (for tests of its choice)
TINY_AUTO = [
    "--examples",
    "300",
    "--epochs",
    "2",
    "--hidden",
    "8",
    "--rollout-steps",
    "0",
    "--quiet",
    "--force",
    "--json",
]


def _run(argv: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(argv)
    return rc, buf.getvalue()


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def user_train(tmp_path_factory: pytest.TempPathFactory) -> CliRun:
    """`neuro train --mjcf` on a user's two-hinge arm, once for the module."""
    base = tmp_path_factory.mktemp("cli")
    mjcf = base / "arm_file.xml"
    mjcf.write_text(ARM_XML)
    root = base / "registry"
    rc, out = _run(
        [
            "train",
            "--mjcf",
            str(mjcf),
            "--substeps",
            "10",
            "--out",
            str(root),
            "--examples",
            "400",
            "--epochs",
            "5",
            "--hidden",
            "16",
            "--sampler",
            "spaced",
            "--schedule",
            "cosine",
            "--batch-size",
            "64",
            "--quiet",
            "--json",
            "--force",  # a tiny training: the plumbing is under test, not the accuracy
        ]
    )
    return CliRun(rc, out, root)


def test_train_with_user_mjcf_writes_latest(user_train: CliRun) -> None:
    assert user_train.rc == 0
    assert (user_train.root / "myarm" / "latest").is_file()  # the name comes from the MJCF
    assert (user_train.root / "myarm" / "latest-n10").is_file()
    path = registry.resolve(user_train.root, "myarm")
    manifest = registry.read_manifest(path)
    assert manifest.model == "myarm"
    assert manifest.substeps == 10
    assert manifest.metrics.examples == 400
    assert manifest.train_config.hidden == (16,)
    assert manifest.train_config.max_epochs == 5
    cfg = manifest.train_config
    assert (cfg.sampler, cfg.schedule, cfg.batch_size, cfg.time_budget) == ("spaced", "cosine", 64, 285.0)


def test_train_json_line_describes_the_artifact(user_train: CliRun) -> None:
    summary = _last_json(user_train.stdout)
    assert summary["model"] == "myarm"
    assert summary["substeps"] == 10
    assert Path(summary["artifact"]) == registry.resolve(user_train.root, "myarm")
    assert summary["examples"] == 400
    assert "one_step_rel_error" in summary and "linear_baseline_rel_error" in summary


def test_eval_prints_json_and_writes_plot(user_train: CliRun, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "eval",
            "myarm",
            "--artifacts",
            str(user_train.root),
            "--substeps",
            "10",
            "--trials",
            "3",
            "--steps",
            "200",
            "--json",
        ]
    )
    assert rc == 0
    summary = _last_json(capsys.readouterr().out)
    for key in (
        "model",
        "substeps",
        "one_step_rel_error",
        "linear_baseline_rel_error",
        "rollout_error_curve",
        "rollout_error_at_20s",
    ):
        assert key in summary, key
    assert summary["model"] == "myarm"
    assert summary["substeps"] == 10
    curve = summary["rollout_error_curve"]
    assert len(curve["t"]) == len(curve["error"]) == 200 // 10 + 1
    assert curve["t"][0] == 0.0 and curve["error"][0] == 0.0
    assert curve["t"][1] == pytest.approx(10 * 0.005)  # one super-step of the arm (timestep 0.005)
    assert all(e >= 0.0 for e in curve["error"])
    assert summary["one_step_rel_error"] >= 0.0
    # the same rollouts in physical units: an arm of hinges has joint errors (radians), no root
    physical = summary["physical_errors"]
    assert physical["root_position_m"] is None and physical["attitude_deg"] is None
    assert [e["t_s"] for e in physical["joint_angle_rad"]] == [1.0]  # 200 steps of 0.005 s reach 1 s
    assert 0.0 <= physical["joint_angle_rad"][0]["mean"] <= physical["joint_angle_rad"][0]["p90"] < math.pi
    plot = Path(summary["plot"])
    assert plot == user_train.root / "myarm" / "rollout_error.png"
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ModelEval.model_validate(summary)  # the typed result, as the dashboard reads it
    assert registry.read_eval(registry.resolve(user_train.root, "myarm")) is None  # not saved unless asked


def test_eval_save_stores_each_versions_result(
    user_train: CliRun, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["eval", "myarm", "--artifacts", str(user_train.root), "--trials", "2", "--steps", "100"]
    assert main([*argv, "--save", "--json"]) == 0
    summary = ModelEval.model_validate_json(capsys.readouterr().out.strip().splitlines()[-1])
    stored = registry.read_eval(registry.resolve(user_train.root, "myarm", substeps=10))
    assert stored is not None and stored == summary.by_substeps[0]
    assert registry.model_eval(user_train.root, "myarm") == summary.model_copy(
        update={"plot": "myarm/rollout_error.png"}
    )


def test_eval_plot_path_option(
    user_train: CliRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "sub" / "curve.png"
    rc = main(
        [
            "eval",
            "myarm",
            "--artifacts",
            str(user_train.root),
            "--trials",
            "2",
            "--steps",
            "100",
            "--plot",
            str(plot),
        ]
    )
    assert rc == 0
    assert plot.is_file()
    out = capsys.readouterr().out
    assert "one-step rel err" in out  # the table, without --json


def test_bench_reports_single_and_batched(
    trained_pendulum: Trained, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(
        [
            "bench",
            "pendulum-active",
            "--artifacts",
            str(trained_pendulum.root),
            "--batches",
            "1,8",
            "--repeats",
            "1",
            "--json",
        ]
    )
    assert rc == 0
    res = _last_json(capsys.readouterr().out)
    assert res["model"] == "pendulum-active"
    assert [row["substeps"] for row in res["single"]] == registry.available_substeps(
        trained_pendulum.root, "pendulum-active"
    )
    bench = ModelBench.model_validate(res)
    assert bench.batched_version == registry.latest_version(trained_pendulum.root, "pendulum-active", 10)
    for row in res["single"]:
        assert row.keys() >= {"substeps", "physics_s", "emulator_s", "ratio"}
        assert row["physics_s"] > 0 and row["emulator_s"] > 0
        assert row["ratio"] == pytest.approx(row["physics_s"] / row["emulator_s"])
    assert [row["batch"] for row in res["batched"]] == [1, 8]
    for row in res["batched"]:
        assert row.keys() >= {"batch", "physics_steps_per_s", "emulator_steps_per_s", "ratio"}
        assert row["physics_steps_per_s"] > 0 and row["emulator_steps_per_s"] > 0


def test_models_lists_catalog_and_user_models(user_train: CliRun, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["models", "--artifacts", str(user_train.root), "--json"]) == 0
    rows = {r["model"]: r["trained"] for r in _last_json(capsys.readouterr().out)}
    assert {"pendulum-passive", "pendulum-active", "pendulum-force", "lander", "truck"} <= rows.keys()
    assert rows["myarm"] == "10"
    assert rows["lander"] is None


def test_models_catalog_prints_only_the_catalog_names(capsys: pytest.CaptureFixture[str]) -> None:
    """What the Makefile and the stack read: one catalog name per line, nothing else."""
    assert main(["models", "--catalog"]) == 0
    assert capsys.readouterr().out.splitlines() == list(catalog.CATALOG)


# ---------------------------------------------------------------------------- bad input
def test_train_unknown_model_exits_2_naming_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["train", "no-such-model", "--out", str(tmp_path), "--quiet"])
    assert rc == 2
    assert "no-such-model" in caplog.text
    assert list(tmp_path.iterdir()) == []


def test_eval_unknown_model_exits_2_naming_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["eval", "ghost-model", "--artifacts", str(tmp_path)])
    assert rc == 2
    assert "ghost-model" in caplog.text


def test_bench_unknown_model_exits_2_naming_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["bench", "ghost-model", "--artifacts", str(tmp_path)])
    assert rc == 2
    assert "ghost-model" in caplog.text


def test_train_refuses_a_rollout_phase_of_no_time(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["train", "dolphin", "--rollout-seconds", "0", "--out", str(tmp_path), "--quiet"])
    assert rc == 2
    assert "--rollout-seconds must be above 0, got 0.0" in caplog.text
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["dolphin", "--state-noise", "1.5"], "--state-noise must be between 0 and 1, got 1.5"),
        (["pendulum-passive", "--state-noise", "0.1"], "pendulum-passive is emulated by one network"),
    ],
)
def test_train_refuses_state_noise_it_cannot_use(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, args: list[str], message: str
) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["train", *args, "--out", str(tmp_path), "--quiet"])
    assert rc == 2
    assert message in caplog.text
    assert list(tmp_path.iterdir()) == []


def test_train_malformed_mjcf_exits_2(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body>")
    with caplog.at_level(logging.ERROR):
        rc = main(["train", "--mjcf", str(bad), "--out", str(tmp_path / "out"), "--quiet"])
    assert rc == 2
    assert "bad.xml is not XML: no element found: line 1" in caplog.text
    assert not (tmp_path / "out").exists()


def test_train_missing_mjcf_exits_2(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(
            ["train", "--mjcf", str(tmp_path / "absent.xml"), "--out", str(tmp_path / "out"), "--quiet"]
        )
    assert rc == 2
    assert "absent.xml" in caplog.text


def test_train_model_and_mjcf_together_exit_2(
    arm_path: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR):
        rc = main(["train", "lander", "--mjcf", str(arm_path), "--out", str(tmp_path / "out"), "--quiet"])
    assert rc == 2
    assert "--mjcf" in caplog.text
    assert not (tmp_path / "out").exists()


def test_train_without_model_or_mjcf_exits_2(tmp_path: Path) -> None:
    assert main(["train", "--out", str(tmp_path / "out"), "--quiet"]) == 2


def test_diverging_training_exits_2_and_writes_nothing(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "out"
    with caplog.at_level(logging.ERROR):
        rc = main(
            [
                "train",
                "pendulum-active",
                "--substeps",
                "10",
                "--examples",
                "300",
                "--epochs",
                "5",
                "--hidden",
                "16",
                "--optimizer",
                "sgd",
                "--lr",
                "1e6",
                "--out",
                str(out),
                "--quiet",
            ]
        )
    assert rc == 2
    assert "diverged" in caplog.text
    assert not out.exists()


def test_unknown_command_is_a_usage_error() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fly"])
    assert exc.value.code == 2


def test_train_zero_substeps_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:  # argparse rejects it before anything runs
        main(["train", "pendulum-active", "--substeps", "0", "--examples", "300", "--epochs", "1",
              "--hidden", "8", "--out", str(out), "--quiet"])  # fmt: skip
    assert exc.value.code == 2
    assert "--substeps" in capsys.readouterr().err
    assert not out.exists()


def test_train_refuses_the_policy_registrys_name_before_training(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "arm.xml").write_text(ARM_XML)
    out = tmp_path / "out"
    args = ["train", "--mjcf", str(tmp_path / "arm.xml"), "--name", "policies", "--out", str(out), "--quiet"]
    assert main(args) == 2
    assert "policy registry" in caplog.text
    assert not out.exists()  # nothing trained, nothing written


def test_train_frame_skip_and_rollout_options_reach_the_manifest(tmp_path: Path) -> None:
    """--frame heading --no-skip --rollout-steps 0 trains the older form of the emulator (the default,
    the body frame with the linear path, is checked in tests/test_body_frame.py)."""
    small = ["--substeps", "10", "--examples", "300", "--epochs", "2", "--hidden", "8", "--quiet", "--force"]
    options = ["--frame", "heading", "--no-skip", "--rollout-steps", "0"]
    assert main(["train", "lander", *small, *options, "--out", str(tmp_path)]) == 0
    older = registry.read_manifest(registry.resolve(tmp_path, "lander"))
    assert (older.emulator.only().frame.body, older.emulator.only().skip) == (False, False)
    assert (older.train_config.frame, older.train_config.skip, older.train_config.rollout_steps) == (
        "heading",
        False,
        0,
    )


def test_an_emulator_that_misses_the_bar_is_refused_and_nothing_written(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    mjcf = tmp_path / "arm.xml"
    mjcf.write_text(ARM_XML)
    out = tmp_path / "out"
    tiny = ["--substeps", "10", "--examples", "300", "--epochs", "2", "--hidden", "8", "--quiet"]
    with caplog.at_level(logging.ERROR):
        rc, stdout = _run(["train", "--mjcf", str(mjcf), *tiny, "--out", str(out), "--json"])
    assert rc == 2
    assert "misses the bar" in caplog.text and "--force" in caplog.text
    assert not (out / "myarm").exists()
    # with --json, what was measured comes out too, marked refused
    refused = _last_json(stdout)
    assert refused["accepted"] is False and "misses the bar" in refused["reason"]
    assert refused["model"] == "myarm" and refused["one_step_rel_error"] > 0 and "artifact" not in refused


def test_auto_super_step_probes_a_model_without_contacts_or_limits_from_50(tmp_path: Path) -> None:
    """A smooth model is probed too, longest first: its first probe usually reaches the bar."""
    mjcf = tmp_path / "arm.xml"
    mjcf.write_text(ARM_XML)
    rc, stdout = _run(
        ["train", "--mjcf", str(mjcf), "--substeps", "auto", *TINY_AUTO, "--out", str(tmp_path)]
    )
    assert rc == 0
    summary = _last_json(stdout)
    reason = summary["substeps_reason"]
    assert summary["substeps"] in (50, 25, 10)
    assert reason.startswith(f"n={summary['substeps']}: contacts in 0% and limits engaged in 0%")
    assert "probe one-step errors n=50:" in reason
    manifest = registry.read_manifest(registry.resolve(tmp_path, "myarm"))
    assert (
        manifest.substeps == summary["substeps"]
        and manifest.metrics.model_dump()["substeps_reason"] == summary["substeps_reason"]
    )


def test_auto_super_step_probes_a_model_whose_limits_engage_without_contact(tmp_path: Path) -> None:
    from tests.helpers import RAIL_XML

    mjcf = tmp_path / "rail.xml"
    mjcf.write_text(RAIL_XML)
    rc, stdout = _run(["train", "--mjcf", str(mjcf), *TINY_AUTO, "--out", str(tmp_path)])  # --mjcf: auto
    assert rc == 0
    summary = _last_json(stdout)
    reason = summary["substeps_reason"]
    assert summary["substeps"] in (50, 25, 10)
    assert "contacts in 0%" in reason and "limits engaged in" in reason
    assert "probe one-step errors n=50:" in reason


def test_auto_super_step_probes_a_model_with_contact(tmp_path: Path) -> None:
    mjcf = Path(__file__).parent / "data" / "pushed_ball.xml"
    rc, stdout = _run(["train", "--mjcf", str(mjcf), *TINY_AUTO, "--out", str(tmp_path)])
    assert rc == 0
    summary = _last_json(stdout)
    reason = summary["substeps_reason"]
    assert "contacts in" in reason and "probe one-step errors n=" in reason
    assert summary["substeps"] in (50, 25, 10)


def test_train_runner_uses_its_data_source_and_its_settings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``neuro train runner``: the runner's data come from its running controller and its settings from
    its data source (``runner_data.TRAIN_DEFAULTS``), except what the command line gives; the result is
    the articulated hierarchy of five networks."""
    rc = main(
        ["train", "runner", "--out", str(tmp_path), "--examples", "1500", "--max-seconds", "3",
         "--hidden", "16", "--branch-hidden", "8,8", "--batch-size", "128", "--loop-tolerance", "0.5",
         "--force", "--quiet", "--json"]
    )  # fmt: skip
    assert rc == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["substeps"] == 6 and summary["examples"] == 1500
    # the kept epoch weighed by the runner's loop check: every epoch's loop error in metres, each run's
    # capped (so tiny an emulator runs far from MuJoCo)
    curve = summary["loop_curve"]
    assert curve and all(row[2] is not None and 0 < row[2] <= 2.0 for row in curve)
    assert summary["loop_kept_epoch"] in [row[0] for row in curve]
    assert set(summary["networks"]) == {"trunk", "left_arm", "right_arm", "left_leg", "right_leg"}
    manifest = registry.read_manifest(registry.resolve(tmp_path, "runner"))
    cfg = manifest.train_config
    assert (
        cfg.hidden == (16,) and cfg.max_seconds == 3 and cfg.time_budget is None and cfg.batch_size == 128
    )  # given on the command line
    assert cfg.limits is False and cfg.rollout_steps == 0 and cfg.activation == "silu"  # the source's
    widths = {n.name: tuple(n.hidden) for n in manifest.emulator.networks}
    assert widths == {
        "trunk": (16,),
        **{f"{s}_{limb}": (8, 8) for s in ("left", "right") for limb in ("arm", "leg")},
    }
    # the feet's height above the floor, chosen from the data: the geoms that come near it
    trunk = next(n for n in manifest.emulator.networks if n.name == "trunk")
    assert cfg.clearance is True and trunk.clearance is not None
    probed = set(trunk.clearance.geoms)
    assert {"left_foot", "right_toes"} <= probed and not {"pelvis", "torso"} & probed
    assert "contact_fraction" not in summary  # no probe of typical controls: the spec gives n


def test_options_given_on_the_command_line_are_never_overridden_by_a_models_own_settings() -> None:
    """``given_fields``: every ``neuro train`` option that sets a training setting counts as given (a
    runner trained with ``--batch-size`` keeps it, though its data source sets another)."""
    parser = build_parser()
    assert given_fields(parser.parse_args(["train", "runner"])) == set()
    args = parser.parse_args(
        [
            "train",
            "runner",
            "--batch-size",
            "64",
            "--schedule",
            "cosine",
            "--epochs",
            "5",
            "--max-seconds",
            "9",
        ]
    )
    assert given_fields(args) == {"batch_size", "schedule", "max_epochs", "max_seconds", "time_budget"}
    assert given_fields(parser.parse_args(["train", "runner", "--mirror", "on"])) == {"mirror"}
    assert given_fields(parser.parse_args(["train", "runner", "--limits", "on"])) == {"limits"}
    assert given_fields(parser.parse_args(["train", "runner", "--members", "2"])) == {"members"}
    assert given_fields(parser.parse_args(["train", "runner", "--loop-tolerance", "off"])) == {
        "loop_tolerance"
    }
    for bad in ("-0.1", "soon"):
        with pytest.raises(SystemExit):
            parser.parse_args(["train", "runner", "--loop-tolerance", bad])
    # every option named exists on the command line
    train = parser.parse_args(["train", "runner"])
    assert all(hasattr(train, option) for option in CONFIG_OPTIONS.values())
    assert set(CONFIG_OPTIONS) <= set(TrainConfig.__dataclass_fields__)


def test_limits_off_trains_without_the_joint_limit_ramps(tmp_path: Path) -> None:
    """``--limits off`` drops the ramps past each joint's range, which are otherwise read; ``on`` keeps them."""
    from tests.helpers import RAIL_XML

    mjcf = tmp_path / "rail.xml"
    mjcf.write_text(RAIL_XML)
    ramps = {}
    for choice in ("on", "off"):
        out = tmp_path / choice
        rc, _ = _run(["train", "--mjcf", str(mjcf), *TINY_AUTO, "--substeps", "10", "--limits", choice,
                      "--out", str(out)])  # fmt: skip
        assert rc == 0
        manifest = registry.read_manifest(registry.resolve(out, "rail"))
        assert manifest.train_config.limits is (choice == "on")
        ramps[choice] = len(manifest.emulator.networks[0].limits)
    assert ramps["on"] >= 1 and ramps["off"] == 0
