"""bench/driven_serving.py end to end at a tiny scale: ten websocket clients of policy-driven lander
sessions (a policy trained for a moment into a data directory of the test's own), then ten undriven
ones, on a real emulator process over loopback, with the numbers of both in one JSON object."""

from __future__ import annotations

from pathlib import Path

from neuroanimator.artifacts import registry
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.control.policy import PolicySettings, train_policy
from neuroanimator.control.policy_store import save_policy
from tests.helpers import run_bench

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"
PHASE_KEYS = {
    "clients",
    "connected",
    "duration_s",
    "steps",
    "steps_per_s",
    "target_steps_per_s",
    "p50_ms",
    "p99_ms",
    "p99_within_limit",
    "errors",
    "clients_replied",
    "min_replies",
    "client_cpu_pct",
    "server_cpu_pct",
}


def test_driven_and_undriven_clients_all_get_their_states(tmp_path: Path) -> None:
    roots = registry.Roots(tmp_path, ARTIFACTS)
    task = POLICY_TASKS["lander-landing"]
    emulator = registry.resolve(roots, "lander", None, task.substeps)
    settings = PolicySettings(seconds=1, max_iterations=2, refine=False, evaluate_runs=4, refine_runs=4)
    trained = train_policy(task, emulator, settings)
    assert trained.goals is not None
    folder = save_policy(roots, trained, trained.goals)

    lines, r = run_bench(
        "bench/driven_serving.py",
        *("--policy", "lander-landing", "--model", "lander", "--clients", "10", "--rate", "11"),
        *("--duration", "3", "--goal-every", "0.5", "--replicas", "1", "--compare-undriven"),
        *("--data", str(tmp_path), "--artifacts", str(ARTIFACTS), "--force"),
        timeout=120,
    )
    assert r["policy"]["version"] == folder.name and r["policy"]["emulator_version"] == emulator.name
    assert r["policy"]["goal_variables"] == ["position.x", "position.y"]
    assert r["clients"] == 10 and r["rate_hz"] == 11.0 and r["p99_limit_ms"] == 50.0
    for phase in ("driven", "undriven"):
        got = r[phase]
        assert set(got) == PHASE_KEYS, phase
        # every client connected and had every counted step answered (JSON frames: the driven replies
        # are the states of the seq sent, echoing the goal last sent)
        assert got["connected"] == 10 and got["errors"] == 0, (phase, got)
        assert got["clients_replied"] == 10 and got["min_replies"] >= 10, (phase, got)
        # paced at 11 Hz: no client steps faster than its ticks
        assert 0 < got["steps_per_s"] <= 10 * 11 * 1.05, (phase, got)
        assert 0 < got["p50_ms"] <= got["p99_ms"], (phase, got)
    assert any(line.startswith("| driven |") for line in lines)
    assert any(line.startswith("| undriven |") for line in lines)
