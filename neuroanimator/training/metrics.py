"""What a training measures (``TrainResult.metrics``, ``HierarchyResult.metrics``): the fields the
manifest's ``TrainMetrics`` requires, and those kept beside them (each phase's, the hierarchy's, and
the notes of how the network and super-step were chosen). Written to the manifest as they are."""

from __future__ import annotations

from typing import Required, TypedDict


class HeldOutErrors(TypedDict):
    """The relative one-step errors of the trained emulator and of the linear baseline on the held-out
    examples, and of the emulator on the validation rows."""

    one_step_rel_error: float
    linear_baseline_rel_error: float
    validation_rel_error: float


class RolloutMetrics(TypedDict, total=False):
    """The rollout phase's validation loss before and after, and its epochs (none without the phase)."""

    rollout_loss_before: float
    rollout_loss_after: float
    rollout_epochs: int


class LoopChoiceMetrics(TypedDict):
    """The loop check's (``loop_choice``): its tolerance, the kept epoch and its loop error (None when
    none was kept, or its loop was not finite), and every epoch's ``[epoch, validation loss, loop error]``
    (the loop error None where it was not finite)."""

    loop_tolerance: float
    loop_kept_epoch: int | None
    loop_error_kept: float | None
    loop_curve: list[list[float | None]]


class ChoiceNotes(TypedDict, total=False):
    """How the network and the super-step were chosen (``neuro train``), noted in the metrics."""

    network_reason: str
    operating_reason: (
        str  # where a model of one's own was trained to operate, and why (OperatingRecord.describe)
    )
    contact_fraction: float
    limit_fraction: float
    substeps_reason: str


class _Measured(ChoiceNotes, RolloutMetrics, total=False):
    """What every training measures: the fields ``core.manifest.TrainMetrics`` requires (sizes, the
    held-out errors, seconds spent), the rollout phase's when it ran, why sampling was cut short
    (``sampling.SamplingPlan.reason``, when it was), and the notes."""

    weights: Required[int]
    examples: Required[int]
    test_examples: Required[int]
    one_step_rel_error: Required[float]
    linear_baseline_rel_error: Required[float]
    validation_rel_error: Required[float]
    data_seconds: Required[float]
    operating_residual: tuple[float, float]  # normalised residual at the operating point, before/after trim
    train_seconds: Required[float]
    total_seconds: Required[float]
    sampling_reason: str


class TrainingExtras(TypedDict, total=False):
    """What a one-network training measures in some cases only: the loop check's (``LoopChoiceMetrics``,
    when the model has one), an articulated hierarchy's errors network by network
    (``train.network_errors``), why sampling was cut short, and why the network reads the floor's
    clearance or not where the data decided it."""

    loop_tolerance: float
    loop_kept_epoch: int | None
    loop_error_kept: float | None
    loop_curve: list[list[float | None]]
    networks: dict[str, dict[str, float]]
    sampling_reason: str
    clearance_reason: str  # where the data decided whether the network reads the floor's clearance


class TrainingMetrics(_Measured, TrainingExtras, total=False):
    """``TrainResult.metrics``."""


class HierarchyMetrics(_Measured, total=False):
    """``HierarchyResult.metrics``: the worst network's held-out errors as the required ones, and each
    network's (by name), the composed step's, and the same with the spring regulariser (None without
    one)."""

    network_errors: Required[dict[str, dict[str, float]]]
    composed_rel_error: Required[float]
    composed_regularized_rel_error: Required[float | None]
