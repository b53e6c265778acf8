"""Driven step: the batched step of policy-driven sessions against undriven ones, in the service's
stepping core.

    python bench/driven_step.py [--sessions 1,64,1024,4096] [--seconds 2] [--data-dir DIR]
                                [--policy NAME] [--json]

For each batch size B: B sessions of the policy's model (the lander's committed n = 25 emulator by
default) stepped as ONE binary block (``Stepper.step_block``, what a binary ``POST /step`` runs after
parsing), over and over for ``--seconds`` each, the two kinds taking turns of a quarter second:
undriven (the client's controls) and driven by the policy (``--policy``, ``lander-landing`` by
default; it sets the controls in the batcher's tick: the policy and the emulator composed into one
graph, ``export.driven``, one ONNX Runtime call). Rows: µs per batched step, µs per session-step and
``ratio`` = driven / undriven (the target: at most 1.5).

Then the ONNX Runtime calls alone at each B: the emulator, the policy, both one after the other, and
the composed graph the service runs.

The policy is read from ``--data-dir`` (``NEUROANIMATOR_DATA_DIR`` layout: ``policies/lander/...``);
without one, a lander-landing policy is trained here for 3 s into a temporary folder (its quality
does not matter for its cost). A dm_control suite task's policy (``--policy acrobot-swingup``) is
read from the data directory its emulator was trained into (``neuro train --mjcf acrobot.xml
--substeps 5 --out DIR``; ``bench/policies.py --artifacts DIR --save-to DIR`` stores the policy
there), or, when only the emulator is there, one of the task's size is trained for a few seconds.
With ``--json`` the last line is one JSON object: ``rows`` (per B: undriven_us, driven_us, ratio,
and the ORT-only timings) and ``max_ratio``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import POLICY_ONNX, PolicyError, resolve_policy
from neuroanimator.contracts.emulator import PolicyDrive, SessionCreate
from neuroanimator.export.driven import compose_driven
from neuroanimator.export.runtime import session_options
from services.emulator.service import EmulatorService
from services.emulator.settings import Settings

REPO = Path(__file__).resolve().parents[1]
LANDER, SUBSTEPS = "lander-landing", 25
log = logging.getLogger("driven_step")


def model_of(policy: str) -> str:
    """The model a policy task drives: a catalog task's model or a suite task's domain."""
    from neuroanimator.catalog.tasks import POLICY_TASKS
    from neuroanimator.control.suite_tasks import SUITE_TASKS

    if policy in POLICY_TASKS:
        return POLICY_TASKS[policy].model
    if policy in SUITE_TASKS:
        return SUITE_TASKS[policy].domain
    raise SystemExit(f"no policy task {policy!r}: one of {', '.join([*POLICY_TASKS, *SUITE_TASKS])}")


def ensure_policy(data: Path, policy: str) -> Path:
    """The folder of ``policy``'s latest version under ``data``, trained here for a few seconds
    when there is none (the lander's through its committed emulator, a suite task's through the
    emulator in ``data``): its cost depends on its size, not on its training."""
    roots = registry.Roots(data, REPO / "artifacts")
    model = model_of(policy)
    try:
        return resolve_policy(roots, model, policy)
    except PolicyError:
        pass
    if policy != LANDER:
        return brief_reward_policy(roots, policy)
    from neuroanimator.catalog.tasks import POLICY_TASKS
    from neuroanimator.control.policy import PolicySettings, train_policy
    from neuroanimator.control.policy_store import save_policy

    task = POLICY_TASKS[policy]
    path = registry.resolve(roots, model, None, SUBSTEPS)
    log.info("training a %s policy for 3 s through %s", policy, path.name)
    settings = PolicySettings(seconds=60, max_iterations=3, refine=False, evaluate_runs=4, refine_runs=4)
    result = train_policy(task, path, settings)
    assert result.goals is not None
    return save_policy(roots, result, result.goals)


def brief_reward_policy(roots: registry.Roots, name: str) -> Path:
    """A suite task's policy of the task's own size, trained for a few iterations through the task's
    emulator in the data directory, stored there."""
    from dataclasses import replace

    from neuroanimator.control.policy_store import save_reward_policy
    from neuroanimator.control.reward_policy import RewardSettings
    from neuroanimator.control.seed_race import train_reward_policy
    from neuroanimator.control.suite_tasks import SUITE_TASKS

    task = SUITE_TASKS[name]
    try:
        path = registry.resolve(roots, task.domain, None, task.substeps)
    except (FileNotFoundError, LookupError, ValueError) as exc:
        raise SystemExit(
            f"{name}: no {task.domain} emulator at n = {task.substeps} in {roots.data}: train one with "
            f"neuro train --mjcf {task.domain}.xml --substeps {task.substeps} --out {roots.data}"
        ) from exc
    vi = task.value_iteration
    if vi is not None:  # a value fitted in two iterations, copied in one short round
        vi = replace(vi, iterations=2, states=256, check_every=0, episodes=4)
    settings = RewardSettings(
        seconds=5, max_iterations=1, eval_episodes=1, final_episodes=1, refine=False, value_iteration=vi
    )
    log.info("training a %s policy briefly through %s", name, path.name)
    result = train_reward_policy(task, path, settings)
    return save_reward_policy(roots, result, path)


def timed(fn: Callable[[], object], seconds: float) -> float:
    """Mean seconds per call of ``fn`` over about ``seconds`` (after one warm-up call)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        spent = time.perf_counter() - t0
        if spent >= seconds and n >= 3:
            return spent / n


SLICE_S = 0.25  # each kind's turn: short, so the machine's noise falls on both kinds alike


async def stepping_core(
    service: EmulatorService, policy: str, sizes: list[int], seconds: float
) -> dict[int, dict[str, float]]:
    """µs per batched step of B undriven and B policy-driven sessions, for each B.

    Both sets of sessions live side by side and take turns of ``SLICE_S`` until each has been stepped
    for ``seconds``: on a shared, noisy machine a slow spell then weighs on both, not on whichever kind
    happened to be measured during it, and the ratio is the cost of driving, not of the moment."""
    out: dict[int, dict[str, float]] = {}
    model = model_of(policy)
    version = service.policies.get(model, policy).manifest.emulator_version
    emu = service.registry.get(model, version)
    goal = [1.0, -2.0] if policy == LANDER else None  # a landing spot; a suite task's own default
    rng = np.random.default_rng(0)
    for b in sizes:
        steps: dict[str, Callable[[], Any]] = {}
        ids: list[str] = []
        for kind in ("undriven", "driven"):
            drive = PolicyDrive(name=policy, goal=goal) if kind == "driven" else None
            kind_ids = [
                service.create_session(SessionCreate(model=model, version=version, seed=i, policy=drive)).id
                for i in range(b)
            ]
            ids += kind_ids
            _, res = service.store.resolve(kind_ids)
            lo, hi = emu.inputs.low, emu.inputs.high
            rows = rng.uniform(lo, hi, (b, len(lo))).astype(np.float32)

            def step(res: Any = res, rows: NDArray[np.float32] = rows) -> Any:
                return service.stepper.step_block(res, rows, lambda i: ("", ""))

            steps[kind] = step
        pool = service.store.pools[(model, version)]
        starts = pool.states.copy()
        spent = dict.fromkeys(steps, 0.0)
        count = dict.fromkeys(steps, 0)
        for run in steps.values():
            await run()  # warm-up
        while min(spent.values()) < seconds or min(count.values()) < 3:
            for kind, run in steps.items():
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < SLICE_S or count[kind] < 3:
                    await run()
                    count[kind] += 1
                    # back to the starts now and then: the lander must not fly off
                    if count[kind] % 20 == 0:
                        pool.states[:] = starts
                        pool.diverged[:] = False
                spent[kind] += time.perf_counter() - t0
        row = {f"{kind}_us": spent[kind] / count[kind] * 1e6 for kind in steps}
        for sid in ids:
            service.delete(sid)
        row["ratio"] = row["driven_us"] / row["undriven_us"]
        out[b] = row
        log.info("B=%d: %s", b, row)
    return out


def ort_only(
    policy_dir: Path, emulator_onnx: Path, sizes: list[int], seconds: float
) -> dict[int, dict[str, float]]:
    """µs per call: the emulator, the policy, both in turn, and the composed graph, at each B."""
    opts = session_options(1)
    pol = ort.InferenceSession(str(policy_dir / POLICY_ONNX), opts, providers=["CPUExecutionProvider"])
    emu = ort.InferenceSession(str(emulator_onnx), opts, providers=["CPUExecutionProvider"])
    limits = registry.read_manifest(emulator_onnx.parent).controls
    graph = compose_driven(
        (policy_dir / POLICY_ONNX).read_bytes(),
        emulator_onnx.read_bytes(),
        [c.low for c in limits],
        [c.high for c in limits],
    )
    both = ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
    s = int(emu.get_inputs()[0].shape[1])
    u = int(pol.get_outputs()[0].shape[1])
    g = int(next(i for i in pol.get_inputs() if i.name == "goal").shape[1])
    rng = np.random.default_rng(0)
    out = {}
    reads_time = any(i.name == "time_left" for i in pol.get_inputs())
    for b in sizes:
        x = rng.normal(size=(b, s)).astype(np.float32)
        goal = rng.normal(size=(b, g)).astype(np.float32)
        # a timed policy (the landing) also reads the time left until its check
        extra = {"time_left": np.full((b, 1), 0.5, np.float32)} if reads_time else {}

        def emulator(x: NDArray[np.float32] = x) -> object:
            return emu.run(None, {"state": x, "controls": np.zeros((len(x), u), np.float32)})

        def policy(
            x: NDArray[np.float32] = x, goal: NDArray[np.float32] = goal, extra: dict[str, Any] = extra
        ) -> object:
            return pol.run(None, {"state": x, "goal": goal, **extra})

        def in_turn(
            x: NDArray[np.float32] = x, goal: NDArray[np.float32] = goal, extra: dict[str, Any] = extra
        ) -> object:
            c = pol.run(None, {"state": x, "goal": goal, **extra})[0]
            return emu.run(None, {"state": x, "controls": c})

        def merged(
            x: NDArray[np.float32] = x, goal: NDArray[np.float32] = goal, extra: dict[str, Any] = extra
        ) -> object:
            return both.run(None, {"state": x, "goal": goal, **extra})

        sep = pol.run(None, {"state": x, "goal": goal, **extra})[0]
        one = both.run(None, {"state": x, "goal": goal, **extra})
        low, high = [c.low for c in limits], [c.high for c in limits]
        np.testing.assert_allclose(one[0], np.clip(sep, low, high), rtol=1e-5, atol=1e-5)  # the same controls
        out[b] = {
            f"ort_{name}_us": timed(fn, seconds / 4) * 1e6
            for name, fn in (
                ("emulator", emulator),
                ("policy", policy),
                ("in_turn", in_turn),
                ("composed", merged),
            )
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", default="1,64,1024,4096", help="batch sizes B, comma-separated")
    ap.add_argument("--seconds", type=float, default=2.0, help="wall time per measurement")
    ap.add_argument("--data-dir", type=Path, help="a data directory holding the policy (module doc)")
    ap.add_argument("--policy", default=LANDER, help="the driving policy's task (default: lander-landing)")
    ap.add_argument("--json", action="store_true", help="print one JSON object last")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sizes = [int(v) for v in args.sessions.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data_dir or Path(tmp)
        folder = ensure_policy(data, args.policy)
        settings = Settings(
            artifacts_dir=REPO / "artifacts",
            data_dir=data,
            redis_url="",
            api_keys="",
            max_sessions=2 * max(sizes) + 10,
            max_batch=max(4096, max(sizes)),
        )
        service = EmulatorService(settings)
        core = asyncio.run(stepping_core(service, args.policy, sizes, args.seconds))
        model = model_of(args.policy)
        emulator_onnx = service.registry.get(
            model, service.policies.get(model, args.policy).manifest.emulator_version
        )
        calls = ort_only(folder, emulator_onnx.path / registry.ONNX_FILE, sizes, args.seconds)
    rows = [{"sessions": b, **core[b], **calls[b]} for b in sizes]
    print("| B | undriven µs/step | driven µs/step | ratio | µs/session-step undriven → driven |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        b = r["sessions"]
        print(
            f"| {b} | {r['undriven_us']:,.0f} | {r['driven_us']:,.0f} | {r['ratio']:.2f} | "
            f"{r['undriven_us'] / b:,.2f} → {r['driven_us'] / b:,.2f} |"
        )
    print("\nONNX Runtime alone, µs per call (1 thread):")
    print("| B | emulator | policy | policy then emulator | composed graph |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['sessions']} | {r['ort_emulator_us']:,.0f} | {r['ort_policy_us']:,.0f} | "
            f"{r['ort_in_turn_us']:,.0f} | {r['ort_composed_us']:,.0f} |"
        )
    result = {"model": model, "policy": args.policy, "rows": rows, "max_ratio": max(r["ratio"] for r in rows)}
    print(f"\nlargest ratio driven / undriven: {result['max_ratio']:.2f} (target: at most 1.5)")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
