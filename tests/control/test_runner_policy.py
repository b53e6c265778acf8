"""The runner's learned running policy (``control.runner_policy``): its data come from the committed
emulator driven by the running controller, then by the policy with the controller's labels; it is
judged on MuJoCo with the pushes the runner's benches use. Small budgets: what it learns at this
size is not the point (``bench/runner_policy.py`` measures that)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator.artifacts import registry
from neuroanimator.catalog.runner import gait as rc
from neuroanimator.control.runner_policy import (
    RUNNER_RUN,
    DistillSettings,
    Ensemble,
    PolicyController,
    collect,
    collect_on_mujoco,
    distill,
    emulator_step,
    judge,
    session_starts,
)
from neuroanimator.control.suite_tasks import Context
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"


@pytest.fixture(scope="module")
def runner() -> tuple[Path, PhysicalModel]:
    path = registry.resolve(ARTIFACTS, "runner")
    return path, registry.load_physical_model(path, registry.read_manifest(path))


def test_the_controllers_runs_on_the_emulator_label_every_state_with_its_targets(
    runner: tuple[Path, PhysicalModel],
) -> None:
    path, model = runner
    step = emulator_step(OnnxEmulator(path / registry.ONNX_FILE, threads=1))
    speeds = np.array([1.8, 2.2])
    runs = collect(model, step, 6, speeds, 1.0, np.random.default_rng(0))
    periods = round(1.0 / (6 * model.mj_model.opt.timestep))
    assert runs.fell == 0
    assert runs.states.shape == (2 * periods, model.state_size)
    assert runs.labels.shape == (2 * periods, model.num_controls)
    assert sorted(set(runs.speeds.tolist())) == [1.8, 2.2]
    ctl = rc.RunnerController(model.mj_model)
    assert np.all(runs.labels >= ctl.low - 1e-9) and np.all(runs.labels <= ctl.high + 1e-9)
    # the runs move forward, each at about its command
    x = runs.states[:, 0].reshape(periods, 2)
    assert np.all(x[-1] > x[0] + 1.0)


def test_a_distilled_policy_acts_within_the_controls_and_reads_the_command(
    runner: tuple[Path, PhysicalModel],
) -> None:
    path, model = runner
    settings = DistillSettings(runs=4, seconds=1.0, rounds=1, epochs=2, hidden=(32,))
    result = distill(path, settings)
    assert len(result.rounds) == 2 and result.rounds[1]["mix"] == settings.mix
    assert result.rounds[1]["examples"] > result.rounds[0]["examples"]
    assert result.emulated_steps == result.rounds[1]["examples"]
    assert result.kept_round == 0  # no round had the policy drive alone: the last fit is kept
    start = model.from_physics(rc.running_start(model.mj_model, 2.0)[None])
    s = torch.as_tensor(np.repeat(start, 2, axis=0), dtype=torch.float32)
    with torch.no_grad():
        u = result.policy(s, torch.tensor([[1.8], [2.2]])).numpy()
    low, high = result.policy.output_range()
    assert np.all(u >= np.array(low) - 1e-6) and np.all(u <= np.array(high) + 1e-6)
    assert not np.allclose(u[0], u[1])  # the command is an input


def test_an_ensemble_policy_averages_its_members_and_is_served_as_one_graph(
    runner: tuple[Path, PhysicalModel], tmp_path: Path
) -> None:
    import onnxruntime as ort

    from neuroanimator.artifacts.policies import POLICY_ONNX
    from neuroanimator.control.policy_store import save_commanded_policy
    from neuroanimator.core.policy_manifest import PolicyMetrics

    path, model = runner
    policy = distill(
        path, DistillSettings(runs=2, seconds=0.5, rounds=0, epochs=1, hidden=(16,), members=3)
    ).policy
    assert isinstance(policy.net, Ensemble) and len(policy.net.members) == 3
    starts = session_starts(model, count=2)
    x = policy.features(torch.as_tensor(starts, dtype=torch.float32), torch.tensor([[2.0], [2.0]]))
    with torch.no_grad():
        each = [net(x) for net in policy.net.members]
        assert not torch.allclose(each[0], each[1])  # members start from their own weights
        torch.testing.assert_close(policy.net(x), torch.stack(each).mean(dim=0))
        want = policy(torch.as_tensor(starts, dtype=torch.float32), torch.tensor([[2.0], [2.0]])).numpy()
    folder = save_commanded_policy(
        registry.Roots(tmp_path, ARTIFACTS), RUNNER_RUN, policy, registry.read_manifest(path), PolicyMetrics()
    )
    graph = ort.InferenceSession(str(folder / POLICY_ONNX), providers=["CPUExecutionProvider"])
    got = graph.run(None, {"state": starts.astype(np.float32), "goal": np.full((2, 1), 2.0, np.float32)})[0]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_of_the_rounds_the_policy_drove_alone_the_one_that_fell_least_is_kept(
    runner: tuple[Path, PhysicalModel],
) -> None:
    path, _model = runner
    settings = DistillSettings(runs=4, seconds=3.0, rounds=3, mix=1.0, epochs=1, hidden=(16,), mujoco_every=0)
    result = distill(path, settings)
    fell = [r["fell"] for r in result.rounds[1:]]
    assert result.kept_round == 1 + int(np.argmin(fell))


def test_mujoco_runs_a_policy_in_the_controllers_place(runner: tuple[Path, PhysicalModel]) -> None:
    """A policy that always gives the standing pose's targets: on MuJoCo the figure stops running."""
    _path, model = runner
    m = model.mj_model
    stand = rc.RunnerController(m).stand

    class Standing(torch.nn.Module):
        def forward(self, s: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
            return torch.as_tensor(stand, dtype=torch.float32).expand(len(s), -1)

    start = rc.running_start(m, 2.0)[None]
    held = rc.run(
        m, start, 2.0, 1.0, control_every=6, kinematic=True, threads=1,
        controller=PolicyController(model, Standing(), np.array([2.0])),  # type: ignore[arg-type]
    )  # fmt: skip
    np.testing.assert_allclose(held.controls[0], np.repeat(stand[None], len(held.controls[0]), axis=0))
    ran = rc.run(m, start, 2.0, 1.0, control_every=6, kinematic=True, threads=1)
    assert not np.allclose(ran.controls, held.controls)


def test_the_judge_counts_the_controllers_pushed_runs_and_their_speed(
    runner: tuple[Path, PhysicalModel],
) -> None:
    _path, model = runner
    row = judge(model, 6, None, 1.8, runs=4, seconds=2.0)
    assert row["runs"] == 4 and row["up"] == 4
    assert row["mean_speed"] is not None and 1.3 < row["mean_speed"] < 2.2
    assert 0 <= row["met"] <= row["up"]


def test_the_policys_own_mujoco_runs_are_labelled_by_the_controller_while_up(
    runner: tuple[Path, PhysicalModel],
) -> None:
    """With the policy in none of the steps the runs are the controller's own: every state kept,
    each label the targets the controller applied there."""
    path, model = runner
    policy = distill(path, DistillSettings(runs=2, seconds=0.5, rounds=0, epochs=1, hidden=(16,))).policy
    speeds = np.array([1.8, 2.0])
    runs = collect_on_mujoco(model, 6, speeds, 1.0, np.random.default_rng(1), policy, mix=0.0)
    periods = round(1.0 / (6 * model.mj_model.opt.timestep))
    assert runs.fell == 0 and runs.states.shape == (2 * periods, model.state_size)
    x = runs.states[:, 0].reshape(2, periods)  # (runs, periods), each run's states in order
    assert np.all(np.diff(x, axis=1) > 0)  # running forward
    ctl = rc.RunnerController(model.mj_model)
    assert np.all(runs.labels >= ctl.low - 1e-9) and np.all(runs.labels <= ctl.high + 1e-9)


def test_the_task_pays_for_running_at_the_command_and_nothing_once_down(
    runner: tuple[Path, PhysicalModel],
) -> None:
    path, model = runner
    ctx = Context(model.mj_model, list(registry.read_manifest(path).layout))
    s = torch.as_tensor(model.from_physics(rc.running_start(model.mj_model, 2.0)[None]).repeat(3, axis=0))
    p = torch.tensor([[2.0], [1.0], [2.0]], dtype=s.dtype)
    s[2, ctx.column("root.pos") + 2] = 0.3  # the pelvis on the ground
    r = RUNNER_RUN.reward(ctx, s, torch.zeros(3, model.num_controls), p, False).numpy()
    assert r[0] == pytest.approx(1.0) and r[1] == 0.0 and r[2] == 0.0
    _qpos, qvel, params = RUNNER_RUN.reset(model.mj_model, np.random.default_rng(0))
    assert RUNNER_RUN.param_low[0] <= params[0] <= RUNNER_RUN.param_high[0]
    assert qvel[0] == pytest.approx(params[0], abs=0.05)


def test_the_bench_learns_and_judges_the_policy_beside_the_controller(tmp_path: Path) -> None:
    from neuroanimator.artifacts.policies import read_policy
    from tests.helpers import run_bench

    lines, result = run_bench(
        "bench/runner_policy.py", "--quick", "--speeds", "1.8,2.2", "--save-to", str(tmp_path)
    )
    assert lines[0].startswith("runner n6-")
    (row,) = result["tasks"]
    assert row["settings"]["mujoco_every"] == 2  # every other round on MuJoCo...
    assert row["task"] == "runner-run" and row["mujoco_steps"] == 0  # ... and one round only, the emulator's
    assert [c["speed"] for c in row["commands"]] == [1.8, 2.2]
    assert [c["runs"] for c in row["controller"]["commands"]] == [4, 4]
    assert 0.0 <= row["success_physics"] <= row["up_physics"] <= 1.0
    assert row["controller"]["success_physics"] > 0  # the controller runs 1 s at 1.8 m/s
    assert row["emulated_steps"] == row["rounds"][-1]["examples"]
    assert row["root_drift_1s_m"] >= 0.0  # the emulator beside MuJoCo under the policy
    stored = read_policy(Path(row["stored"]))
    assert Path(row["stored"]).is_relative_to(tmp_path)  # the user's data directory, not the tree
    assert stored.name == "runner-run" and stored.metrics.success_physics == row["success_physics"]
    assert len(stored.starts) == 8 and len(stored.starts[0]) == stored.state_size  # where sessions start


def test_a_stored_runner_policy_drives_a_session_at_the_speed_it_is_sent(
    runner: tuple[Path, PhysicalModel], tmp_path: Path
) -> None:
    """Stored as a commanded policy, it is served as the others are: a session created with it and a
    command, stepped over REST, gets the policy's targets every super-step; it starts at one of the
    policy's own starts (running, drawn by the seed), not standing; a command outside the range it
    learned is flagged."""
    from fastapi.testclient import TestClient

    from neuroanimator.artifacts.policies import POLICY_ONNX
    from neuroanimator.control.policy_store import save_commanded_policy
    from neuroanimator.core.policy_manifest import PolicyMetrics
    from services.emulator.app import create_app
    from services.emulator.settings import Settings

    path, model = runner
    emulator = registry.read_manifest(path)
    policy = distill(path, DistillSettings(runs=2, seconds=0.5, rounds=0, epochs=1, hidden=(16,))).policy
    roots = registry.Roots(tmp_path, ARTIFACTS)
    starts = session_starts(model, count=3)
    folder = save_commanded_policy(
        roots, RUNNER_RUN, policy, emulator, PolicyMetrics(success_physics=0.0), starts=starts
    )
    drive = {"name": "runner-run", "version": folder.name}
    import onnxruntime as ort

    graph = ort.InferenceSession(str(folder / POLICY_ONNX), providers=["CPUExecutionProvider"])
    settings = Settings(
        artifacts_dir=ARTIFACTS, data_dir=tmp_path, max_wait_ms=1.0, registry_poll_s=0.0,
        redis_url="", api_keys="", api_key_secret="test-secret",
    )  # fmt: skip
    with TestClient(create_app(settings)) as client:
        r = client.post("/sessions", json={"model": "runner", "seed": 5, "policy": {**drive, "goal": [2.1]}})
        assert r.status_code == 201, r.text
        info = r.json()
        np.testing.assert_allclose(info["state"], starts[5 % 3], atol=1e-5)  # the seed's start
        assert info["state"][emulator.state_labels.index("root.vel.x")] == pytest.approx(2.0, abs=0.05)
        assert info["policy"]["goal_variables"] == ["speed"] and info["policy"]["goal"] == [
            pytest.approx(2.1)
        ]
        state = np.asarray(info["state"], np.float32)
        r = client.post(f"/sessions/{info['id']}/step", json={"forces": [0.0, 0.0]})
        assert r.status_code == 200, r.text
        want = graph.run(None, {"state": state[None], "goal": np.array([[2.1]], np.float32)})[0][0]
        np.testing.assert_allclose(r.json()["controls"][0], want, rtol=1e-4, atol=1e-4)
        r = client.post("/sessions", json={"model": "runner", "policy": {**drive, "goal": [3.0]}})
        assert r.status_code == 201 and r.json()["policy"]["goal_outside"] == ["speed"]
