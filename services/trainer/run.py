"""One training, in a process of its own: ``python -m services.trainer.run < spec.json``.

A training job's process (``execution.perform``) starts this and reads what it says; it is killed when
the training is cancelled, runs past its time limit or its worker shuts down. It reads the training's
spec (JSON) on stdin and goes through the phases:

- **validating**: the model is read from the upload (``mjcf.load_mjcf``: includes, assets, archives,
  with the service's caps) around its operating point (the training's operating spec and keyframe, as
  the API checked them) and checked as the API checked it; then a short probe simulates typical
  motion, so that a model that diverges fails now (naming the time and the joint, and what to try), and
  one that would sample too slowly for the time limit fails now too (with the estimate);
- **sampling** and **training**: ``neuro train`` (the command's own code: the same choices of super-step,
  network and acceptance bar; the operating spec in ``SPEC_FILE`` of the staging folder, ``--spec``)
  into a staging registry;
- **evaluating**: ``neuro eval --save`` of that version: one-step errors on fresh held-out data and
  rollouts against MuJoCo in physical units (``eval.json`` beside the version).

It writes one JSON object per line on stdout: ``{"phase", "percent", "detail", "losses"}`` as it goes
(``losses``: new ``[epoch, validation loss]`` points), then ``{"result": {...}}``, or ``{"error":
"..."}`` when the training cannot succeed (then exit status 2). Everything else (logs) goes to stderr.
Progress is read from the progress bars of ``neuroanimator`` (``tqdm``, replaced here by ``Bar``
before anything imports it), so training code needs no hooks for it.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from pydantic import BaseModel, Field, TypeAdapter

from services.trainer.spec import ChildSpec, TrainedEmulator

# Phases' share of the percent: validating up to 2, sampling up to 30, training up to 85, evaluating up
# to 95; the job's process exports the artifact (95 to 100).
SHARES = {
    "validating": (0.0, 2.0),
    "sampling": (2.0, 30.0),
    "training": (30.0, 85.0),
    "evaluating": (85.0, 95.0),
}
EPOCHS_SHARE = 0.85  # of the training phase, the one-step epochs; the rest for the rollout phase
REPORT_EVERY_S = 0.5
PROBE_RUNS = 16
PROBE_SECONDS = 2.0
SAMPLING_SHARE_OF_LIMIT = 0.6  # sampling may take at most this part of the time limit
TEST_EXAMPLES = 4000  # TrainConfig's held-out examples (read from it in main)
SPEC_FILE = "operating-spec.json"  # the training's operating spec, in its staging folder, for neuro train


class Channel:
    """The JSON lines to the job's process, and the state they describe."""

    def __init__(self, out: IO[str]) -> None:
        self.out = out
        self.lock = threading.Lock()
        self.phase = "validating"
        self.percent = 0.0
        self.detail = ""
        self.losses: list[list[float | None]] = []
        self.sent_at = 0.0
        self.stage = "validating"  # validating, train or evaluating: what the bars belong to
        self.sampled_before = 0  # examples of earlier sampling bars (the training set, then the test set)
        self.sampling_total = 1

    def send(self, obj: dict[str, object]) -> None:
        with self.lock:
            self.out.write(json.dumps(obj, allow_nan=False, default=str) + "\n")
            self.out.flush()

    def progress(self, phase: str, fraction: float, detail: str, force: bool = False) -> None:
        """Report ``fraction`` (0..1) of ``phase`` done; at most every ``REPORT_EVERY_S`` unless the
        phase changed, ``force`` or new loss points wait."""
        lo, hi = SHARES[phase]
        percent = max(self.percent, lo + (hi - lo) * min(1.0, max(0.0, fraction)))
        changed = phase != self.phase
        self.phase, self.percent, self.detail = phase, percent, detail
        now = time.monotonic()
        if not (changed or force or now - self.sent_at >= REPORT_EVERY_S):
            return
        self.sent_at = now
        losses, self.losses = self.losses, []
        self.send({"phase": phase, "percent": round(percent, 2), "detail": detail, "losses": losses})


CHANNEL: Channel | None = None


def _number(text: Any) -> float | None:
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


class Bar:
    """Stands in for ``tqdm.tqdm``: draws nothing, tells ``CHANNEL`` how far a bar got (sampling
    examples, training epochs and their validation loss). Takes what tqdm takes. A bar tqdm would not
    show (``disable``) belongs to a side computation, e.g. the short probe trainings that choose the
    super-step: it counts for nothing but says what is going on."""

    def __init__(
        self,
        iterable: Iterable[Any] | None = None,
        desc: str | None = None,
        total: float | None = None,
        disable: bool | None = False,
        **_: Any,
    ) -> None:
        self.quiet = bool(disable)
        self.iterable = iterable
        self.desc = desc or ""
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total = float(total or 0)
        self.n = 0
        self.started = time.monotonic()
        self.left_s: float | None = None  # of the time cap, when the loop says (``left`` in its postfix)
        self._report()

    def __iter__(self) -> Iterator[Any]:
        for item in self.iterable or ():
            yield item
            self.n += 1
            self._report()

    def __enter__(self) -> Bar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return int(self.total)

    def update(self, n: float = 1) -> None:
        self.n += int(n)
        self._report()

    def set_postfix(
        self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True, **kw: Any
    ) -> None:
        values = {**(ordered_dict or {}), **kw}
        c = CHANNEL
        if c is not None and self.desc == "training" and "val" in values and not self.quiet:
            c.losses.append([self.n + 1, _number(values["val"])])
        if "left" in values:  # seconds left of the training's time cap
            self.left_s = _number(str(values["left"]).rstrip("s"))
        self._report()

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def close(self) -> None:
        c = CHANNEL
        if c is not None and self.desc.startswith("sampling") and c.stage == "train" and not self.quiet:
            c.sampled_before += self.n  # the next sampling bar (the held-out set) counts on from here
            self.n = 0
        self._report(force=True)

    def refresh(self, *args: Any, **kw: Any) -> None:
        """Nothing to draw."""

    def clear(self, *args: Any, **kw: Any) -> None:
        """Nothing to clear."""

    @classmethod
    def write(cls, s: str, *args: Any, **kw: Any) -> None:
        sys.stderr.write(s + "\n")

    def fraction(self) -> float:
        """How far the training loop is, by whichever of its epochs and its time cap runs out first."""
        by_epochs = self.n / self.total if self.total else 0.0
        if self.left_s is None:
            return by_epochs
        spent = time.monotonic() - self.started
        return max(by_epochs, spent / max(1e-9, spent + self.left_s))

    def training_detail(self) -> str:
        if self.left_s is not None and self.total and self.fraction() > self.n / self.total:
            return f"epoch {self.n}; about {self.left_s:.0f} s of the training's time cap left"
        return f"epoch {self.n} of at most {int(self.total)}"

    def _report(self, force: bool = False) -> None:
        c = CHANNEL
        if c is None:
            return
        with contextlib.suppress(Exception):  # progress is best effort: it never breaks a training
            if self.quiet:
                if c.stage == "train" and c.phase != "training":
                    c.progress("sampling", 0.0, "choosing the super-step: short probe trainings", force)
            elif c.stage == "train" and self.desc.startswith("sampling"):
                done = c.sampled_before + self.n
                train = c.sampling_total - TEST_EXAMPLES  # the budget asked for; the held-out set after it
                detail = (
                    f"sampling: {done:,} of {train:,} training examples"
                    if done <= train
                    else f"sampling the held-out set: {done - train:,} of {TEST_EXAMPLES:,} examples"
                )
                c.progress("sampling", done / c.sampling_total, detail, force)
            elif c.stage == "train" and self.desc.startswith("sequences"):
                c.progress(
                    "training", EPOCHS_SHARE, f"sampling rollouts: {self.n:,} of {int(self.total):,}", force
                )
            elif c.stage == "train" and self.desc == "training" and self.total:
                c.progress("training", EPOCHS_SHARE * self.fraction(), self.training_detail(), force)


def install_bars() -> None:
    """Replace ``tqdm.tqdm`` by ``Bar`` before ``neuroanimator`` imports it."""
    import tqdm

    tqdm.tqdm = Bar


class LastError(logging.Handler):
    """Keeps the last error logged (``neuro`` logs why a training stopped, e.g. it diverged)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.message: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        self.message = record.getMessage()


class Failed(Exception):
    """The training cannot succeed; the message says why and what to try."""


# ---------------------------------------------------------------------------- the phases
def probe(model: Any, spec: ChildSpec, substeps: int) -> None:
    """Simulate a few runs of typical motion: ``SimulationDiverged`` (the time and the joint) when the
    model is unstable; ``Failed`` when sampling the budget would take too much of the time limit."""
    import numpy as np

    rng = np.random.default_rng(0)
    steps = max(10, round(PROBE_SECONDS / model.dt))
    times = np.arange(steps, dtype=np.float64) * model.dt
    s0 = model.initial_states(rng, PROBE_RUNS)
    u = model.typical_controls(rng, PROBE_RUNS, times)
    f = model.typical_forces(rng, PROBE_RUNS, times)
    from neuroanimator.sim import sampling  # after main has put Bar in tqdm's place

    model.simulate(s0[:1], u[:1, :10], f[:1, :10] if model.num_forces else None, check=True)  # warm up
    model.simulate(s0, u, f if model.num_forces else None, check=True)
    rate = model.measure_step_rate()  # the warm-up (one run) does not count
    # the runs that hold the examples, then the held-out set; the rollout phase cuts windows of the runs
    examples = spec.examples
    needed = round(sampling.sampling_steps(model, substeps, examples, TEST_EXAMPLES))
    estimate = needed / rate
    allowed = SAMPLING_SHARE_OF_LIMIT * spec.time_limit_s
    if estimate > allowed:
        raise Failed(
            f"model {model.name} samples too slowly for the time limit: {examples:,} examples at super-step "
            f"{substeps} need about {needed:,} physical steps, about {estimate:,.0f} s at the {rate:,.0f} "
            f"steps/s it simulates here, and sampling may take {allowed:,.0f} s of the {spec.time_limit_s:,.0f} s "
            "limit (JOB_TIMEOUT_S). Try a smaller sample budget (examples), a shorter super-step, a larger "
            "timestep in the MJCF, or fewer contacts"
        )


def train_argv(spec: ChildSpec, staging: Path) -> list[str]:
    """``neuro train``'s arguments for the spec (its operating spec in ``SPEC_FILE`` of ``staging``,
    where ``write_spec`` puts it)."""
    argv = ["train", "--mjcf", spec.source, "--name", spec.model, "--out", str(staging), "--json"]
    argv += ["--examples", str(spec.examples), "--substeps", str(spec.super_step)]
    if spec.entry:
        argv += ["--entry", spec.entry]
    if spec.operating_spec is not None:
        argv += ["--spec", str(staging / SPEC_FILE)]
    if spec.keyframe is not None:
        argv += ["--keyframe", spec.keyframe]
    for value, flag in (
        (spec.epochs, "--epochs"),
        (spec.hidden, "--hidden"),
        (spec.rollout_steps, "--rollout-steps"),
    ):
        if value is not None:
            argv += [flag, str(value)]
    if spec.force:
        argv.append("--force")
    return argv


def write_spec(spec: ChildSpec, staging: Path) -> None:
    """Write the training's operating spec (if it has one) where ``train_argv`` names it."""
    if spec.operating_spec is not None:
        (staging / SPEC_FILE).write_text(spec.operating_spec)


# ``neuro``'s advice names its flags; a training through the service is asked for with the form's fields
# (the dashboard's Add-a-model labels in brackets)
SERVICE_WORDS = (
    (
        "--force writes it anyway",
        'force=true keeps it anyway ("keep the emulator even if it misses the accuracy bar")',
    ),
    ("--substeps", "super_step (Super-step)"),
    ("--examples", "examples (Sample budget)"),
    ("--hidden", "hidden (Hidden layers)"),
    ("--epochs", "epochs (Epochs)"),
    ("--rollout-steps", "rollout_steps (Rollout steps)"),
    ("--entry", "entry (Entry XML)"),
    ("--name", "name (Name)"),
    ("--spec", "operating_spec (Operating spec)"),
    ("--keyframe", "keyframe"),
)


def in_service_words(message: str) -> str:
    """A message of ``neuro``'s with its flags named as the service's form fields."""
    for flag, words in SERVICE_WORDS:
        message = message.replace(flag, words)
    return message


def run_command(argv: list[str], errors: LastError) -> str:
    """Run a ``neuro`` command in this process; its standard output. ``Failed`` with its reason."""
    from neuroanimator import cli
    from neuroanimator.artifacts import registry
    from neuroanimator.sim.model import ModelError

    args = cli.build_parser().parse_args(argv)
    buffer = io.StringIO()
    errors.message = None
    try:
        with contextlib.redirect_stdout(buffer):
            rc = int(args.func(args))
    except (ModelError, registry.ArtifactError, ValueError) as exc:
        raise Failed(str(exc)) from exc
    if rc != 0:
        raise Failed(errors.message or f"neuro {argv[0]} ended with status {rc}")
    return buffer.getvalue()


class Trained(BaseModel):
    """What ``neuro train --json`` prints last (the fields read here; it prints more)."""

    artifact: str = Field(description="the version's folder")
    data_seconds: float | None = None
    one_step_rel_error: float | None = None
    linear_baseline_rel_error: float | None = None
    weights: int | None = None
    examples: int | None = None
    substeps_reason: str | None = None
    network_reason: str | None = None
    clearance_reason: str | None = None
    operating_reason: str | None = None


def last_json(text: str) -> Trained:
    for line in reversed(text.splitlines()):
        if line.startswith("{"):
            return Trained.model_validate_json(line)
    raise Failed("neuro printed no result")


def run(spec: ChildSpec, channel: Channel, errors: LastError) -> TrainedEmulator:
    """The phases (see the module's text); the result."""
    from neuroanimator.artifacts import registry
    from neuroanimator.core.operating_spec import OperatingSpec
    from neuroanimator.sim.bundle import Limits
    from neuroanimator.sim.mjcf import load_mjcf
    from services.trainer.validation import check_trainable

    seconds: dict[str, float] = {}
    t0 = time.monotonic()
    channel.progress("validating", 0.0, "reading the model", force=True)
    model = load_mjcf(
        spec.source,
        entry=spec.entry,
        name=spec.model,
        limits=TypeAdapter(Limits).validate_python(spec.limits),
        operating_spec=(
            None if spec.operating_spec is None else OperatingSpec.model_validate_json(spec.operating_spec)
        ),
        keyframe=spec.keyframe,
    )
    check_trainable(model)
    channel.progress("validating", 0.3, "simulating typical motion", force=True)
    n = spec.super_step if isinstance(spec.super_step, int) else 50
    probe(model, spec, n)
    seconds["validating"] = time.monotonic() - t0

    staging = Path(spec.staging)
    write_spec(spec, staging)
    argv = train_argv(spec, staging)
    channel.stage = "train"
    channel.sampling_total = spec.examples + TEST_EXAMPLES
    channel.progress("sampling", 0.0, "sampling", force=True)
    t1 = time.monotonic()
    trained = last_json(run_command(argv, errors))
    train_s = time.monotonic() - t1
    data_s = float(trained.data_seconds or 0.0)
    seconds["sampling"], seconds["training"] = data_s, max(0.0, train_s - data_s)

    channel.stage = "evaluating"
    channel.progress("evaluating", 0.0, "rollouts against MuJoCo", force=True)
    t2 = time.monotonic()
    version_dir = Path(trained.artifact)
    manifest = registry.read_manifest(version_dir)
    steps = max(1, round(spec.eval_seconds / manifest.timestep))
    evaluate = ["eval", spec.model, "--artifacts", str(staging), "--substeps", str(manifest.substeps)]
    evaluate += ["--trials", str(spec.eval_trials), "--steps", str(steps), "--save"]
    run_command(evaluate, errors)
    seconds["evaluating"] = time.monotonic() - t2
    found = registry.read_eval(version_dir)
    return TrainedEmulator(
        model=manifest.model,
        version=manifest.version,
        substeps=manifest.substeps,
        one_step_rel_error=found.one_step_rel_error if found else trained.one_step_rel_error,
        linear_baseline_rel_error=(
            found.linear_baseline_rel_error if found else trained.linear_baseline_rel_error
        ),
        physical_errors=found.physical_errors if found else None,
        weights=trained.weights,
        examples=trained.examples,
        phase_seconds={k: round(v, 2) for k, v in seconds.items()},
        notes=[
            *(
                [f"super-step {manifest.substeps}: {trained.substeps_reason}"]
                if trained.substeps_reason
                else []
            ),
            *([f"network {trained.network_reason}"] if trained.network_reason else []),
            *([trained.clearance_reason] if trained.clearance_reason else []),
            *([trained.operating_reason] if trained.operating_reason else []),
        ],
    )


def main() -> int:
    global CHANNEL, TEST_EXAMPLES
    events = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1)
    sys.stdout = sys.stderr  # whatever prints goes to the log, never into the events
    install_bars()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    errors = LastError()
    logging.getLogger().addHandler(errors)
    spec = ChildSpec.model_validate_json(sys.stdin.read())
    from neuroanimator.core.train_config import TrainConfig
    from neuroanimator.sim.model import ModelError

    TEST_EXAMPLES = TrainConfig().test_examples
    CHANNEL = channel = Channel(events)
    try:
        result = run(spec, channel, errors)
    except (Failed, ModelError) as exc:
        channel.send({"error": in_service_words(str(exc))})
        return 2
    channel.send({"result": result.model_dump()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
