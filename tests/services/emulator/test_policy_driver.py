"""A policy-driven session: a trained feedback policy (``neuro policy``) sets the controls every
super-step from the session's state and goal, on every transport, in one policy call per tick; the
client sends goals and forces, never controls; a MuJoCo shadow runs the same policy on its own state.

Over the committed lander emulator at n = 25 and a policy trained through it for 3 s (once for the
module), beside a timed variant whose network is the untrained one of the same shape (what matters
here is that its ``time_left`` input is fed as the service promises, not how well it lands).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import pytest
import torch
from fastapi.testclient import TestClient
from numpy.typing import NDArray

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import POLICY_ONNX, read_policy
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.control.policy import PolicySettings, train_policy
from neuroanimator.control.policy_net import PolicyNet
from neuroanimator.control.policy_store import save_policy
from neuroanimator.export.runtime import OnnxEmulator
from services.emulator import batcher as batcher_module
from services.emulator import binary
from services.emulator.app import create_app
from services.emulator.settings import Settings
from tests.helpers import app_state, run_bench, service_of

ARTIFACTS = Path(__file__).resolve().parents[3] / "artifacts"
OLDER_N25 = "n25-20261121T144545"  # a committed lander version the policy was not trained through
Floats = NDArray[np.float32]


@dataclass
class Policies:
    """The module's data directory and the folders of its two policies."""

    data: Path
    landing: Path
    timed: Path
    emulator: Path  # the artifact they were trained through


@pytest.fixture(scope="module")
def policies(tmp_path_factory: pytest.TempPathFactory) -> Policies:
    data = tmp_path_factory.mktemp("policy-data")
    roots = registry.Roots(data, ARTIFACTS)
    # the landing untimed (the catalog's reads the time left): the timed variant is made below
    task = replace(POLICY_TASKS["lander-landing"], timed=False)
    path = registry.resolve(roots, "lander", None, task.substeps)
    settings = PolicySettings(seconds=60, max_iterations=2, refine=False, evaluate_runs=4, refine_runs=4)
    result = train_policy(task, path, settings)
    assert result.goals is not None
    landing = save_policy(roots, result, result.goals)
    # a timed policy: a goal every 5 s, judged 4 s after it is set (20 and 16 super-steps of 0.25 s)
    timed_task = replace(task, name="lander-timed", timed=True, goal_period_s=5.0, check_after_s=4.0)
    torch.manual_seed(0)
    net = PolicyNet(replace(result.net.shape, timed=True))
    last = net.mlp[-1]
    assert isinstance(last, torch.nn.Linear)
    torch.nn.init.normal_(last.weight, std=0.5)  # (so that its controls move with time_left)
    timed = save_policy(roots, replace(result, net=net, task=timed_task), result.goals)
    return Policies(data, landing, timed, path)


@pytest.fixture
def client(policies: Policies) -> Iterator[TestClient]:
    settings = Settings(
        artifacts_dir=ARTIFACTS,
        data_dir=policies.data,
        max_wait_ms=1.0,
        registry_poll_s=0.0,
        redis_url="",
        api_keys="",
        api_key_secret="test-secret",
    )
    with TestClient(create_app(settings)) as c:
        yield c


class Reference:
    """The policy and the emulator evaluated here, apart from the service."""

    def __init__(self, folder: Path, emulator: Path) -> None:
        self.manifest = read_policy(folder)
        self.session = ort.InferenceSession(str(folder / POLICY_ONNX), providers=["CPUExecutionProvider"])
        self.emulator = OnnxEmulator(emulator / registry.ONNX_FILE)

    def controls(self, state: list[float], goal: list[float], since_goal: int = 0) -> Floats:
        """(U,) the policy's controls for one state and goal, ``since_goal`` super-steps after it was set."""
        m = self.manifest
        feed = {"state": np.asarray([state], np.float32), "goal": np.asarray([goal], np.float32)}
        if m.timed:
            left = max(0, m.check_steps - since_goal) / m.goal_period_steps
            feed["time_left"] = np.asarray([[left]], np.float32)
        out: Floats = self.session.run(None, feed)[0][0]
        return out

    def step(self, state: list[float], controls: Floats) -> Floats:
        out: Floats = self.emulator.step(np.asarray([state], np.float32), controls[None])[0]
        return out


def _create(client: TestClient, policy: dict[str, Any], seed: int = 1) -> dict[str, Any]:
    r = client.post("/sessions", json={"model": "lander", "seed": seed, "policy": policy})
    assert r.status_code == 201, r.text
    info: dict[str, Any] = r.json()
    return info


def test_a_policy_drives_a_rest_session_towards_the_goal_it_is_given(
    client: TestClient, policies: Policies
) -> None:
    ref = Reference(policies.landing, policies.emulator)
    m = ref.manifest
    info = _create(client, {"name": "lander-landing"})
    # no version named: the session runs the emulator version the policy was trained through
    assert info["version"] == m.emulator_version == policies.emulator.name
    assert info["policy"] == {
        "name": "lander-landing",
        "version": m.version,
        "emulator_version": m.emulator_version,
        "goal_variables": ["position.x", "position.y"],
        "goal": [float(np.float32(v)) for v in m.goal_default],
        "goal_low": m.goal_low,
        "goal_high": m.goal_high,
        "goal_default": m.goal_default,
        "goal_outside": [],
        "timed": False,
    }
    sid, state = info["id"], info["state"]
    assert isinstance(state, list)
    goal = [3.0, -4.0]
    r = client.post(f"/sessions/{sid}/step", json={"goal": goal, "steps": 3})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["goal"] == goal and body["goal_outside"] == [] and len(body["controls"]) == 3
    for k in range(3):  # each super-step: the policy's controls for the state it starts from
        want = ref.controls(state, goal)
        np.testing.assert_allclose(body["controls"][k], want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(body["states"][k], ref.step(state, want), rtol=1e-4, atol=1e-4)
        state = body["states"][k]
    # the goal is held: a step without one goes on towards it, and the session says so
    r = client.post(f"/sessions/{sid}/step", json={})
    assert r.status_code == 200 and r.json()["goal"] == goal
    np.testing.assert_allclose(r.json()["controls"][0], ref.controls(state, goal), rtol=1e-5, atol=1e-5)
    assert client.get(f"/sessions/{sid}").json()["policy"]["goal"] == goal


def test_a_goal_outside_the_trained_goals_is_accepted_and_flagged(client: TestClient) -> None:
    info = _create(client, {"name": "lander-landing", "goal": [40.0, 0.0]})
    assert info["policy"]["goal_outside"] == ["position.x"]
    sid = info["id"]
    r = client.post(f"/sessions/{sid}/step", json={"goal": [0.0, -40.0]})
    assert r.status_code == 200 and r.json()["goal_outside"] == ["position.y"]
    r = client.post(f"/sessions/{sid}/step", json={"goal": [0.0, 0.0]})
    assert r.status_code == 200 and r.json()["goal_outside"] == []
    assert client.get(f"/sessions/{sid}").json()["policy"]["goal_outside"] == []


def test_bad_policy_requests_are_named(client: TestClient, policies: Policies) -> None:
    m = read_policy(policies.landing)
    r = client.post("/sessions", json={"model": "lander", "policy": {"name": "lander-hover"}})
    assert r.status_code == 404 and r.json()["error"] == "unknown_policy"
    assert "lander-hover" in r.json()["message"] and "lander-landing" in r.json()["message"]
    r = client.post(
        "/sessions", json={"model": "lander", "policy": {"name": "lander-landing", "version": "p-1"}}
    )
    assert r.status_code == 404 and r.json()["field"] == "policy.version"
    # a session of another emulator version is refused, naming both
    r = client.post(
        "/sessions", json={"model": "lander", "version": OLDER_N25, "policy": {"name": "lander-landing"}}
    )
    assert r.status_code == 409, r.text
    assert r.json()["message"] == (
        f"policy 'lander-landing' was trained for emulator version {m.emulator_version}; "
        f"this session runs {OLDER_N25}"
    )
    for goal, field, expected, got in (
        ([1.0, 2.0, 3.0], "policy.goal", 2, 3),
        ([1e39, 0.0], "policy.goal[0]", "a finite float32", 1e39),
    ):
        r = client.post(
            "/sessions", json={"model": "lander", "policy": {"name": "lander-landing", "goal": goal}}
        )
        assert r.status_code == 422, r.text
        assert (r.json()["field"], r.json()["expected"], r.json()["got"]) == (field, expected, got)
    r = client.post(
        "/sessions", json={"model": "lander", "policy": {"name": "lander-landing", "goal": ["NaN", 0]}}
    )
    assert r.status_code == 422
    r = client.post("/sessions", json={"model": "lander", "driver": {}, "policy": {"name": "lander-landing"}})
    assert r.status_code == 422 and r.json()["error"] == "driver_and_policy"

    sid = _create(client, {"name": "lander-landing"})["id"]
    before = client.get(f"/sessions/{sid}").json()
    r = client.post(f"/sessions/{sid}/step", json={"controls": [16.0, 0.0, 0.0, 0.0]})
    assert (
        r.status_code == 422
        and r.json()["error"] == "policy_sets_controls"
        and r.json()["field"] == "controls"
    )
    r = client.post(f"/sessions/{sid}/step", json={"goal": [1.0]})
    assert r.status_code == 422 and (r.json()["field"], r.json()["expected"], r.json()["got"]) == (
        "goal",
        2,
        1,
    )
    after = client.get(f"/sessions/{sid}").json()
    assert after["steps"] == before["steps"] == 0 and after["policy"]["goal"] == before["policy"]["goal"]
    # a session without a policy takes no goal
    plain = client.post(
        "/sessions", json={"model": "lander", "version": m.emulator_version, "seed": 2}
    ).json()
    r = client.post(f"/sessions/{plain['id']}/step", json={"controls": [16.0, 0, 0, 0], "goal": [0.0, 0.0]})
    assert r.status_code == 422 and r.json()["error"] == "no_policy"


def test_a_policy_drives_a_websocket_session_and_its_mujoco_shadow(
    client: TestClient, policies: Policies
) -> None:
    ref = Reference(policies.landing, policies.emulator)
    info = _create(client, {"name": "lander-landing", "goal": [2.0, 2.0]})
    sid, state = info["id"], info["state"]
    assert isinstance(state, list)
    shadow = state
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_json({"type": "start", "mode": "lockstep", "shadow": True})
        assert ws.receive_json()["shadow"] is True
        for k, goal in enumerate(([2.0, 2.0], [-5.0, 1.0], [-5.0, 1.0])):
            ws.send_json({"type": "step", "goal": goal, "seq": k} if k else {"type": "step", "seq": k})
            msg = ws.receive_json()
            assert msg["type"] == "state" and msg["seq"] == k and msg["goal"] == goal, msg
            np.testing.assert_allclose(msg["controls"], ref.controls(state, goal), rtol=1e-5, atol=1e-5)
            # the shadow's own copy of the policy reads the shadow's MuJoCo state, with the same goal
            twin = msg["shadow"]
            np.testing.assert_allclose(twin["controls"], ref.controls(shadow, goal), rtol=1e-5, atol=1e-5)
            state, shadow = msg["state"], twin["state"]
        assert np.linalg.norm(np.subtract(state[:3], shadow[:3])) < 0.5  # both fly the same course
        ws.send_json({"type": "step", "controls": [16.0, 0, 0, 0], "seq": 7})
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "policy_sets_controls" and err["seq"] == 7
        ws.send_json({"type": "controls", "goal": [0.0], "seq": 8})
        err = ws.receive_json()
        assert err["type"] == "error" and err["field"] == "goal" and err["expected"] == 2
        # a binary frame's control values are ignored: the policy sets them
        ws.send_json({"type": "start", "shadow": False})
        ws.receive_json()
        ws.send_bytes(binary.encode_ws_frame(9, np.asarray([1e6, 1e6, 1e6, 1e6], np.float32)))
        msg = ws.receive_json()
        assert msg["seq"] == 9 and msg["clipped"] is False, msg
        want = ref.controls(state, [-5.0, 1.0])
        np.testing.assert_allclose(msg["controls"], want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(msg["state"], ref.step(state, want), rtol=1e-4, atol=1e-4)
    assert client.get(f"/sessions/{sid}").json()["steps"] == 4


def test_one_policy_call_per_policy_in_a_tick_and_undriven_sessions_unaffected(
    client: TestClient, policies: Policies
) -> None:
    landing = Reference(policies.landing, policies.emulator)
    timed = Reference(policies.timed, policies.emulator)
    goals = [[float(i), -float(i)] for i in range(6)]
    driven = [_create(client, {"name": "lander-landing", "goal": g}, seed=i) for i, g in enumerate(goals)]
    ticking = [_create(client, {"name": "lander-timed", "goal": [1.0, 1.0]}, seed=10 + i) for i in range(2)]
    version = landing.manifest.emulator_version
    plain = [
        client.post("/sessions", json={"model": "lander", "version": version, "seed": 20 + i}).json()
        for i in range(3)
    ]
    everyone = driven + ticking + plain
    service = service_of(client)
    loaded = {p.name: p for p in service.policies.loaded.values()}
    calls = {name: p.calls for name, p in loaded.items()}
    ort_calls = service.stepper.ort_calls
    rows = np.zeros((len(everyone), 4), np.float32)
    rows[len(driven) + len(ticking) :] = [[16.0, 0.01, -0.02, 0.0]] * len(plain)
    rows[: len(driven)] = np.nan  # the control values of a policy's row are ignored, NaN included
    r = client.post(
        "/step",
        content=binary.encode_batch_request([str(s["id"]) for s in everyone], rows),
        headers={"content-type": binary.MEDIA_TYPE},
    )
    assert r.status_code == 200, r.text
    status, states = binary.decode_batch_response(r.content)
    assert status.tolist() == [binary.OK] * len(everyone)
    # one ORT call for the emulator, and one for each policy over all of its sessions
    assert service.stepper.ort_calls == ort_calls + 1
    assert {name: p.calls - calls[name] for name, p in loaded.items()} == {
        "lander-landing": 1,
        "lander-timed": 1,
    }
    for s, g, new in zip(driven, goals, states, strict=False):
        want = landing.controls(s["state"], g)
        np.testing.assert_allclose(new, landing.step(s["state"], want), rtol=1e-4, atol=1e-4)
    for s, new in zip(ticking, states[len(driven) :], strict=False):
        want = timed.controls(s["state"], [1.0, 1.0], 0)
        np.testing.assert_allclose(new, timed.step(s["state"], want), rtol=1e-4, atol=1e-4)
    for s, new, u in zip(
        plain, states[len(driven) + len(ticking) :], rows[len(driven) + len(ticking) :], strict=True
    ):
        np.testing.assert_allclose(new, landing.step(s["state"], u), rtol=1e-5, atol=1e-5)


def test_a_bad_goal_is_its_own_sessions_error_in_a_batch(client: TestClient, policies: Policies) -> None:
    ref = Reference(policies.landing, policies.emulator)
    good = _create(client, {"name": "lander-landing"}, seed=3)
    bad = _create(client, {"name": "lander-landing"}, seed=4)
    plain = client.post(
        "/sessions", json={"model": "lander", "version": ref.manifest.emulator_version, "seed": 5}
    ).json()
    r = client.post(
        "/step",
        json={
            "items": [
                {"session": good["id"], "goal": [1.0, 1.0]},
                {"session": bad["id"], "goal": [1.0, 1.0, 1.0]},
                {"session": plain["id"], "controls": [16.0, 0.0, 0.0, 0.0]},
            ]
        },
    )
    assert r.status_code == 200, r.text
    ok, err, other = r.json()["results"]
    np.testing.assert_allclose(ok["controls"], ref.controls(good["state"], [1.0, 1.0]), rtol=1e-5, atol=1e-5)
    assert ok["goal"] == [1.0, 1.0] and ok["error"] is None
    assert err["error"]["field"] == "items[1].goal" and err["error"]["got"] == 3 and err["state"] is None
    assert other["error"] is None and other["controls"] is None and other["goal"] is None
    assert client.get(f"/sessions/{bad['id']}").json()["steps"] == 0


def test_a_timed_policy_reads_the_time_since_its_goal_was_set(client: TestClient, policies: Policies) -> None:
    ref = Reference(policies.timed, policies.emulator)
    assert (ref.manifest.goal_period_steps, ref.manifest.check_steps) == (20, 16)
    info = _create(client, {"name": "lander-timed", "goal": [1.0, 2.0]})
    sid, state = info["id"], info["state"]
    assert isinstance(state, list) and info["policy"]["timed"] is True
    since = 0
    plan = [([1.0, 2.0], 18), ([1.0, 2.0], 1), ([-3.0, 0.0], 2)]  # the same goal again keeps the clock
    for goal, steps in plan:
        r = client.post(f"/sessions/{sid}/step", json={"goal": goal, "steps": steps})
        assert r.status_code == 200, r.text
        if goal != [1.0, 2.0]:
            since = 0
        for k in range(steps):
            want = ref.controls(state, goal, since)
            np.testing.assert_allclose(r.json()["controls"][k], want, rtol=1e-5, atol=1e-5)
            state, since = r.json()["states"][k], since + 1
    # the clock mattered: past the check (time_left 0) the controls differ from at the goal's start
    assert not np.allclose(ref.controls(state, [1.0, 2.0], 0), ref.controls(state, [1.0, 2.0], 17))


def test_a_policy_driven_session_keeps_its_policy_and_goal_across_a_restart(
    policies: Policies, redis_url: str, redis_prefix: str
) -> None:
    """The policy (name and version), the goal and when it was set are checkpointed: a restored timed
    session goes on with the same clock, and a goal changed without a step is checkpointed too."""
    ref = Reference(policies.timed, policies.emulator)
    settings = Settings(
        artifacts_dir=ARTIFACTS,
        data_dir=policies.data,
        redis_url=redis_url,
        redis_prefix=redis_prefix,
        replica_id="p1",
        checkpoint_interval_s=60.0,
        api_keys="",
        api_key_secret="test-secret",
    )

    def checkpoint(c: TestClient) -> int:
        assert c.portal is not None  # the client's lifespan is running
        n: int = c.portal.call(app_state(c).persistence.checkpoint)
        return n

    with TestClient(create_app(settings)) as a:
        sid = _create(a, {"name": "lander-timed", "goal": [1.0, 2.0]})["id"]
        a.post(f"/sessions/{sid}/step", json={"steps": 3})
        assert checkpoint(a) == 1
        with a.websocket_connect(f"/ws/sessions/{sid}") as ws:  # a new goal at step 3, without a step
            ws.send_json({"type": "controls", "goal": [-2.0, 5.0]})
            ws.send_json({"type": "ping", "seq": 1})
            assert ws.receive_json()["type"] == "pong"
        assert checkpoint(a) == 1
        state = a.post(f"/sessions/{sid}/step", json={"steps": 2}).json()["state"]
        assert checkpoint(a) == 1
    with TestClient(create_app(settings)) as b:
        info = b.get(f"/sessions/{sid}").json()
        assert info["steps"] == 5 and info["policy"]["name"] == "lander-timed"
        assert info["policy"]["version"] == ref.manifest.version and info["policy"]["goal"] == [-2.0, 5.0]
        r = b.post(f"/sessions/{sid}/step", json={})
        assert r.status_code == 200, r.text
        # two super-steps since the goal was set: the restored clock goes on
        want = ref.controls(state, [-2.0, 5.0], 2)
        np.testing.assert_allclose(r.json()["controls"][0], want, rtol=1e-5, atol=1e-5)
        assert not np.allclose(want, ref.controls(state, [-2.0, 5.0], 0), atol=1e-4)


def test_the_driven_step_benchmark_runs(policies: Policies) -> None:
    """bench/driven_step.py end to end at a tiny scale, over the module's policy."""
    lines, r = run_bench(
        "bench/driven_step.py", "--sessions", "1,8", "--seconds", "0.05", "--data-dir", str(policies.data)
    )
    assert [row["sessions"] for row in r["rows"]] == [1, 8]
    for row in r["rows"]:
        assert row["driven_us"] > 0 and row["undriven_us"] > 0
        assert row["ratio"] == pytest.approx(row["driven_us"] / row["undriven_us"])
        assert (
            min(row[k] for k in ("ort_emulator_us", "ort_policy_us", "ort_in_turn_us", "ort_composed_us")) > 0
        )
    assert r["max_ratio"] == max(row["ratio"] for row in r["rows"])
    assert any("target: at most 1.5" in line for line in lines)


@pytest.mark.parametrize("name", ["lander-landing", "lander-timed"])
def test_a_tick_of_one_policys_sessions_is_one_composed_call(
    client: TestClient, policies: Policies, name: str
) -> None:
    """Every row driven by one policy: the policy and the emulator run as ONE graph (one ONNX
    Runtime call), with the same controls and states as the two calls in turn."""
    ref = Reference(policies.timed if name == "lander-timed" else policies.landing, policies.emulator)
    goals = [[2.0 * i, -1.0 - i] for i in range(5)]
    sessions = [_create(client, {"name": name, "goal": g}, seed=30 + i) for i, g in enumerate(goals)]
    service = service_of(client)
    loaded = next(p for p in service.policies.loaded.values() if p.name == name)
    calls, ort_calls = loaded.calls, service.stepper.ort_calls
    states = _step_all(client, sessions)
    assert service.stepper.ort_calls == ort_calls + 1 and loaded.calls == calls + 1
    batcher = service.stepper._batchers[("lander", ref.manifest.emulator_version)]
    driven = batcher.driven_step(loaded)
    assert driven is not None and driven.calls >= 1  # the tick ran the composed graph
    for s, g, new in zip(sessions, goals, states, strict=True):
        want = np.clip(ref.controls(s["state"], g), *_control_range(ref))
        np.testing.assert_allclose(new, ref.step(s["state"], want), rtol=1e-4, atol=1e-4)
        got = client.get(f"/sessions/{s['id']}").json()
        assert got["steps"] == 1


def test_a_tick_over_the_composed_graphs_rows_runs_the_two_graphs_in_turn(
    client: TestClient, policies: Policies, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Above ``COMPOSED_MAX_ROWS`` rows (where two calls are the faster), a tick of one policy's
    sessions runs the policy, then the emulator: the same states as the composed graph gives."""
    monkeypatch.setattr(batcher_module, "COMPOSED_MAX_ROWS", 2)
    ref = Reference(policies.landing, policies.emulator)
    goals = [[1.0 * i, 2.0 - i] for i in range(5)]
    sessions = [
        _create(client, {"name": "lander-landing", "goal": g}, seed=60 + i) for i, g in enumerate(goals)
    ]
    service = service_of(client)
    loaded = next(p for p in service.policies.loaded.values() if p.name == "lander-landing")
    calls, ort_calls = loaded.calls, service.stepper.ort_calls
    states = _step_all(client, sessions)
    assert (service.stepper.ort_calls, loaded.calls) == (ort_calls + 1, calls + 1)
    batcher = service.stepper._batchers[("lander", ref.manifest.emulator_version)]
    driven = batcher.driven_step(loaded)
    assert driven is not None and driven.calls == 0  # the composed graph was not run
    for s, g, new in zip(sessions, goals, states, strict=True):
        want = np.clip(ref.controls(s["state"], g), *_control_range(ref))
        np.testing.assert_allclose(new, ref.step(s["state"], want), rtol=1e-4, atol=1e-4)


def _step_all(client: TestClient, sessions: list[dict[str, Any]]) -> Floats:
    """(N, S) the new states of one binary batched step of every session (their controls ignored:
    their policies set them); every session answered OK."""
    zeros = np.zeros((len(sessions), 4), np.float32)
    r = client.post(
        "/step",
        content=binary.encode_batch_request([str(s["id"]) for s in sessions], zeros),
        headers={"content-type": binary.MEDIA_TYPE},
    )
    status, states = binary.decode_batch_response(r.content)
    assert status.tolist() == [binary.OK] * len(sessions)
    out: Floats = states
    return out


def _control_range(ref: Reference) -> tuple[Floats, Floats]:
    m = registry.read_manifest(ARTIFACTS / "lander" / ref.manifest.emulator_version)
    return (
        np.array([c.low for c in m.controls], np.float32),
        np.array([c.high for c in m.controls], np.float32),
    )
