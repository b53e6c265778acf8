"""Driven step: the batched step of policy-driven sessions against undriven ones, in the service's
stepping core.

    python bench/driven_step.py [--sessions 1,64,1024,4096] [--seconds 2] [--data-dir DIR] [--json]

For each batch size B: B lander sessions (the committed n = 25 emulator) stepped as ONE binary block
(``Stepper.step_block``, what a binary ``POST /step`` runs after parsing), over and over for
``--seconds`` each, the two kinds taking turns of a quarter second: undriven (the client's controls)
and driven by the ``lander-landing`` policy (the policy sets the controls in the batcher's tick: the
policy and the emulator composed into one graph, ``export.driven``, one ONNX Runtime call). Rows: µs per batched step, µs per session-step and
``ratio`` = driven / undriven (the target: at most 1.5).

Then the ONNX Runtime calls alone at each B: the emulator, the policy, both one after the other, and
the composed graph the service runs.

The policy is read from ``--data-dir`` (``NEUROANIMATOR_DATA_DIR`` layout: ``policies/lander/...``);
without one, a policy is trained here for 3 s into a temporary folder (its quality does not matter
for its cost). With ``--json`` the last line is one JSON object: ``rows`` (per B: undriven_us,
driven_us, ratio, and the ORT-only timings) and ``max_ratio``.
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
MODEL, POLICY, SUBSTEPS = "lander", "lander-landing", 25
log = logging.getLogger("driven_step")


def ensure_policy(data: Path) -> Path:
    """The folder of the lander-landing policy under ``data``, trained here (3 s) when there is none."""
    roots = registry.Roots(data, REPO / "artifacts")
    try:
        return resolve_policy(roots, MODEL, POLICY)
    except PolicyError:
        pass
    from neuroanimator.catalog.tasks import POLICY_TASKS
    from neuroanimator.control.policy import PolicySettings, train_policy
    from neuroanimator.control.policy_store import save_policy

    task = POLICY_TASKS[POLICY]
    path = registry.resolve(roots, MODEL, None, SUBSTEPS)
    log.info("training a %s policy for 3 s through %s", POLICY, path.name)
    settings = PolicySettings(seconds=60, max_iterations=3, refine=False, evaluate_runs=4, refine_runs=4)
    result = train_policy(task, path, settings)
    assert result.goals is not None
    return save_policy(roots, result, result.goals)


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
    service: EmulatorService, sizes: list[int], seconds: float
) -> dict[int, dict[str, float]]:
    """µs per batched step of B undriven and B policy-driven sessions, for each B.

    Both sets of sessions live side by side and take turns of ``SLICE_S`` until each has been stepped
    for ``seconds``: on a shared, noisy machine a slow spell then weighs on both, not on whichever kind
    happened to be measured during it, and the ratio is the cost of driving, not of the moment."""
    out: dict[int, dict[str, float]] = {}
    version = service.policies.get(MODEL, POLICY).manifest.emulator_version
    emu = service.registry.get(MODEL, version)
    rng = np.random.default_rng(0)
    for b in sizes:
        steps: dict[str, Callable[[], Any]] = {}
        ids: list[str] = []
        for kind in ("undriven", "driven"):
            policy = PolicyDrive(name=POLICY, goal=[1.0, -2.0]) if kind == "driven" else None
            kind_ids = [
                service.create_session(SessionCreate(model=MODEL, version=version, seed=i, policy=policy)).id
                for i in range(b)
            ]
            ids += kind_ids
            _, res = service.store.resolve(kind_ids)
            lo, hi = emu.inputs.low, emu.inputs.high
            rows = rng.uniform(lo, hi, (b, len(lo))).astype(np.float32)

            def step(res: Any = res, rows: NDArray[np.float32] = rows) -> Any:
                return service.stepper.step_block(res, rows, lambda i: ("", ""))

            steps[kind] = step
        pool = service.store.pools[(MODEL, version)]
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
    ap.add_argument("--data-dir", type=Path, help="a data directory holding a lander-landing policy")
    ap.add_argument("--json", action="store_true", help="print one JSON object last")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    sizes = [int(v) for v in args.sessions.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data_dir or Path(tmp)
        folder = ensure_policy(data)
        settings = Settings(
            artifacts_dir=REPO / "artifacts",
            data_dir=data,
            redis_url="",
            api_keys="",
            max_sessions=2 * max(sizes) + 10,
            max_batch=max(4096, max(sizes)),
        )
        service = EmulatorService(settings)
        core = asyncio.run(stepping_core(service, sizes, args.seconds))
        emulator_onnx = service.registry.get(
            MODEL, service.policies.get(MODEL, POLICY).manifest.emulator_version
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
    result = {"model": MODEL, "policy": POLICY, "rows": rows, "max_ratio": max(r["ratio"] for r in rows)}
    print(f"\nlargest ratio driven / undriven: {result['max_ratio']:.2f} (target: at most 1.5)")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
