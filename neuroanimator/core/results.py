"""Evaluation and benchmark results of emulators: what ``neuro eval`` and ``neuro bench`` measure.

Each artifact version keeps its own results beside its manifest (``<version>/eval.json``,
``<version>/bench.json``: ``VersionEval``, ``VersionBench``). A model's results over its super-steps
(``ModelEval``, ``ModelBench``: what ``--json`` prints and the dashboard shows) are put together from
the versions that the ``latest-n<N>`` pointers name, by ``summarize_eval`` and ``summarize_bench``.
These types are part of the wire contract (``proto/schemas/results``). Needs only pydantic.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

from pydantic import BaseModel, ConfigDict


class _Result(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RolloutCurve(_Result):
    """Mean normalised rollout error against MuJoCo (thesis Fig. 6.6): ``error[i]`` at ``t[i]`` seconds."""

    t: list[float]
    error: list[float]

    def at(self, seconds: float) -> float:
        """The error at a time, interpolated linearly (held at the ends), as ``numpy.interp`` does."""
        t, e = self.t, self.error
        if seconds <= t[0]:
            return float(e[0])
        if seconds >= t[-1]:
            return float(e[-1])
        i = bisect.bisect_right(t, seconds)  # t[i - 1] <= seconds < t[i]
        w = (seconds - t[i - 1]) / (t[i] - t[i - 1])
        return float(e[i - 1] + w * (e[i] - e[i - 1]))


class NetworkSize(_Result):
    """The emulator's network: hidden widths, activation, parameter count."""

    hidden: list[int]
    activation: str
    weights: int


class PhysicalErrorAt(_Result):
    """An error in physical units at ``t_s`` seconds into the rollouts: mean and 90th percentile over
    the trials; null (an infinite error: JSON has no infinity) where enough emulated rollouts diverged
    to make it so."""

    t_s: float
    mean: float | None
    p90: float | None


class PhysicalErrors(_Result):
    """Rollout errors against MuJoCo in physical units, for the quantities the model has: the root's
    position (metres), its attitude (degrees: the angle between orientations, or between headings) and
    the joints (radians: mean absolute difference of hinge angles and ball-joint rotations; metres: mean
    absolute difference of slide joints and of free bodies' positions other than the root's)."""

    root_position_m: list[PhysicalErrorAt] | None = None
    attitude_deg: list[PhysicalErrorAt] | None = None
    joint_angle_rad: list[PhysicalErrorAt] | None = None
    joint_position_m: list[PhysicalErrorAt] | None = None

    def at(self, quantity: str, seconds: float) -> PhysicalErrorAt | None:
        """The entry of ``quantity`` at ``seconds``, if measured."""
        for e in getattr(self, quantity) or []:
            if math.isclose(e.t_s, seconds):
                return e
        return None


class VersionEval(_Result):
    """One version's accuracy against MuJoCo, on held-out data and in rollouts (``<version>/eval.json``).

    ``baseline_ratio`` is the linear baseline's one-step error over the emulator's; the rollout
    errors are means over trials and state variables, each divided by its standard deviation.
    """

    model: str
    version: str
    substeps: int
    one_step_rel_error: float
    linear_baseline_rel_error: float
    baseline_ratio: float
    rollout_error_curve: RolloutCurve
    rollout_error_at_20s: float
    rollout_error_final: float
    architecture: NetworkSize
    train_seconds: float | None = None
    physical_errors: PhysicalErrors = PhysicalErrors()


class ThesisPreset(_Result):
    """The thesis' network for this model (Table 6.1), for comparison."""

    hidden: list[int] | None
    activation: str = "sigmoid"


class ModelEval(VersionEval):
    """A model's accuracy over its super-steps: the primary version's results at the top level (n = 50
    unless asked otherwise), every version in ``by_substeps`` (by n), the plot of their rollout
    curves, and, with both N^25 and N^100, how N^100's rollout error compares with N^25's."""

    thesis_preset: ThesisPreset
    by_substeps: list[VersionEval]
    plot: str | None = None
    n100_vs_n25_at_20s: float | None = None
    n100_vs_n25_max: float | None = None
    n100_vs_n25_mean: float | None = None


class SingleClientSpeed(_Result):
    """One client: MuJoCo and the emulator covering the same 20,000 physical steps (thesis Table 6.2)."""

    substeps: int
    version: str
    physics_s: float
    emulator_s: float
    ratio: float


class BatchedSpeed(_Result):
    """B clients stepped together: physical steps covered per second by ``mujoco.rollout`` and the emulator."""

    batch: int
    physics_steps_per_s: float
    emulator_steps_per_s: float
    ratio: float


class VersionBench(_Result):
    """One version's speed against MuJoCo (``<version>/bench.json``): a single client, and batched
    when this version was the one batched."""

    model: str
    version: str
    substeps: int
    single: SingleClientSpeed | None = None
    batched: list[BatchedSpeed] = []


class ModelBench(_Result):
    """A model's speed: a single client for every trained n, batched for one n (``batched_substeps``)."""

    model: str
    single: list[SingleClientSpeed] = []
    batched: list[BatchedSpeed] = []
    batched_substeps: int | None = None
    batched_version: str | None = None


def n100_vs_n25(c25: RolloutCurve, c100: RolloutCurve) -> dict[str, float]:
    """Ratio of N^100's to N^25's rollout error at the times both reach (from 5 s on) and at 20 s.

    Thesis 6.1.2: predicting further means fewer iterations, so the error need not grow with n.
    """
    common = [t for t in c100.t if 5.0 <= t <= c25.t[-1]]
    ratios = [c100.at(t) / max(c25.at(t), 1e-12) for t in common]
    return {
        "n100_vs_n25_at_20s": c100.at(20.0) / max(c25.at(20.0), 1e-12),
        "n100_vs_n25_max": max(ratios) if ratios else float("nan"),
        "n100_vs_n25_mean": float(sum(ratios) / len(ratios)) if ratios else float("nan"),
    }


def summarize_eval(
    rows: Sequence[VersionEval],
    thesis_hidden: int | None,
    primary_substeps: int | None = None,
    plot: str | None = None,
) -> ModelEval:
    """A model's evaluation from its versions' (``rows``, any order, at least one).

    ``thesis_hidden`` is the width of the thesis' network for the model (its spec's); the primary
    row is the one for ``primary_substeps`` (default 50), else the last by n.
    """
    if not rows:
        raise ValueError("no evaluated versions to summarise")
    ordered = sorted(rows, key=lambda r: r.substeps)
    want = 50 if primary_substeps is None else primary_substeps
    primary = next((r for r in ordered if r.substeps == want), ordered[-1])
    by_n = {r.substeps: r for r in ordered}
    ratios: dict[str, float | None] = {}
    if {25, 100} <= set(by_n):
        found = n100_vs_n25(by_n[25].rollout_error_curve, by_n[100].rollout_error_curve)
        ratios = {k: v if math.isfinite(v) else None for k, v in found.items()}  # JSON has no NaN
    return ModelEval(
        **primary.model_dump(),
        thesis_preset=ThesisPreset(hidden=[thesis_hidden] if thesis_hidden else None),
        by_substeps=list(ordered),
        plot=plot,
        **ratios,
    )


def summarize_bench(model: str, rows: Sequence[VersionBench]) -> ModelBench:
    """A model's benchmark from its versions' (any order): single-client rows by n, and the batched
    rows of the version that has them (the one with the most rows, then the larger n)."""
    ordered = sorted(rows, key=lambda r: r.substeps)
    single = [r.single for r in ordered if r.single is not None]
    batched = max((r for r in ordered if r.batched), key=lambda r: (len(r.batched), r.substeps), default=None)
    return ModelBench(
        model=model,
        single=single,
        batched=list(batched.batched) if batched else [],
        batched_substeps=batched.substeps if batched else None,
        batched_version=batched.version if batched else None,
    )


def split_bench(bench: ModelBench) -> list[VersionBench]:
    """The per-version records of a model's benchmark, by n."""
    out: dict[int, VersionBench] = {}
    for row in bench.single:
        out[row.substeps] = VersionBench(
            model=bench.model, version=row.version, substeps=row.substeps, single=row
        )
    if bench.batched and bench.batched_substeps is not None and bench.batched_version is not None:
        n = bench.batched_substeps
        record = out.get(n) or VersionBench(model=bench.model, version=bench.batched_version, substeps=n)
        out[n] = record.model_copy(update={"batched": list(bench.batched)})
    return [out[n] for n in sorted(out)]
