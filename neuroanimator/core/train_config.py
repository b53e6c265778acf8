"""``TrainConfig``: everything that decides an emulator, saved in full in every artifact's manifest.

Plain data without torch, so that a manifest (which holds one) can be read by any process.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from pydantic import ConfigDict

# The time budget ``neuro train`` keeps to unless told otherwise (a run under 5 minutes). A larger one
# is used, not only allowed: the examples and both phases' caps grow with it (``TrainConfig.budget_scale``)
DEFAULT_TIME_BUDGET = 285.0


@dataclass
class TrainConfig:
    """Everything that decides an emulator. ``preset="thesis"`` swaps in Table 6.1's network."""

    __pydantic_config__ = ConfigDict(extra="forbid")  # read back from manifests: unknown keys are errors

    substeps: int = 50
    preset: str = "default"  # "default" or "thesis" (one sigmoid hidden layer, Table 6.1 width)
    hidden: tuple[int, ...] = (64, 64)
    # an articulated hierarchy's limb networks (neuroanimator.emulator.articulated), or a hierarchy's part networks
    # (neuroanimator.emulator.hierarchy); None: as wide as ``hidden``
    branch_hidden: tuple[int, ...] | None = None
    activation: str = "tanh"
    # an articulated hierarchy's networks each the mean of this many MLPs, each trained on its own error
    # (an ensemble: neuroanimator.emulator.articulated)
    members: int = 1
    normalization: str = "group"  # "group" (thesis eqs. 4.10-4.11) or "variable"
    examples: int | None = None  # None: examples_per_weight × the network's weights (thesis: 8-10×)
    examples_per_weight: float = 10.0
    # "runs": every super-step of runs driven with held controls (about n physical steps an example);
    # "spaced": thesis 4.5's examples at lags of [Δt, 5Δt] (about 6n); neuroanimator.sim.sampling
    sampler: str = "runs"
    test_examples: int = 4000  # held out: drawn from an independent seed, never trained on
    val_fraction: float = 0.1  # of the training examples, for early stopping
    optimizer: str = "adam"  # "adam" or "sgd" (mini-batch gradient descent with momentum, thesis 4.5.3)
    lr: float = 3e-3
    momentum: float = 0.9
    schedule: str = "plateau"  # "plateau" (halve when stuck) or "cosine" over the epoch/time budget
    batch_size: int = 256
    max_epochs: int = 300
    patience: int = 30  # epochs without a better validation loss before stopping
    max_seconds: float = 150.0  # wall-clock cap on the optimisation loop (keeps a run under 5 min)
    # the kept epoch: None, the lowest validation loss; a fraction t, of the epochs within (1 + t) of
    # it, the one whose closed loop (the data source's loop check) ends nearest MuJoCo's
    # (neuroanimator.training.loop_choice)
    loop_tolerance: float | None = None
    input_noise: float = 0.0  # std of Gaussian noise on normalised state inputs during training
    # a hierarchy's global network trained from states moved by Gaussian noise of this share of each
    # group's change over a super-step, its targets still the true next frames: it learns to pull a
    # drifted body back (as learned simulators are trained), where clean data show it only the
    # simulation's states (the parts' networks, placed in its frames each step, train on clean data)
    state_noise: float = 0.0
    frame: str = "auto"  # "auto"/"body": full body frame for a quaternion root; "heading": yaw only
    skip: bool = True  # a linear path beside the MLP, started from the least-squares fit
    limits: bool = True  # limited joints also enter as ramps past their limits (structured.JointLimit)
    # geoms that can touch the floor enter through their height above it (neuroanimator.emulator.clearance);
    # None: decided by the training data, on where they touch the floor often (clearance.FloorContact);
    # a trained emulator's manifest holds the decision
    clearance: bool | None = None
    # pairs of geoms that touch each other in the data enter through their distance (neuroanimator.emulator.proximity;
    # off by default: measured on dm_control's finger, it did not lower the error)
    proximity: bool = False
    # a left-right symmetric figure: half the examples simulated, the other half their mirror images
    # across the x-z plane (neuroanimator.sim.mirror); a model that is not symmetric is refused
    mirror: bool = False
    # Then train over emulated rollouts of this many super-steps (0: off), so that a long rollout stays
    # on track: one-step training leaves small biases that a rollout integrates into drift.
    rollout_steps: int = 8
    rollout_sequences: int | None = None  # None: one per 16 one-step examples
    rollout_seconds: float = 60.0  # wall-clock cap on the rollout phase
    # The whole training's wall-clock budget, sampling included (None: the phases' own caps only): the
    # rollout phase gets what the data and the one-step phase left of it (at least a third of its cap),
    # and the one-step phase is cut only where sampling alone leaves it less than its cap
    # A budget above the default scales the examples per weight and both phases' caps by how many
    # times the default it is (``budget_scale``): more data is what lowers a contact model's error
    time_budget: float | None = DEFAULT_TIME_BUDGET
    # thesis 6.1.3: Euler steps of a mass-spring model's springs after each emulated super-step (None:
    # the model's own number, ModelSpec.regularizer; 0: off); models without springs ignore it
    regularizer_steps: int | None = None
    seed: int = 0
    threads: int = 2
    progress: bool = True
    thesis_hidden: int | None = field(default=None, repr=False)

    def resolved(self) -> TrainConfig:
        """The config with the preset applied."""
        if self.preset == "thesis":
            width = self.thesis_hidden or 40
            return TrainConfig(
                **{
                    **asdict(self),
                    "hidden": (width,),
                    "branch_hidden": None,
                    "activation": "sigmoid",
                    "preset": "thesis",
                }
            )
        if self.preset != "default":
            raise ValueError(f"preset must be 'default' or 'thesis', got {self.preset!r}")
        return self

    def budget_scale(self) -> float:
        """How many times the default budget ``time_budget`` is, at least 1 (1 without a budget): the
        examples per weight, ``max_seconds`` and ``rollout_seconds`` are multiplied by it, so that a
        larger budget is spent on more data and longer training, not left unused."""
        if self.time_budget is None:
            return 1.0
        return max(1.0, self.time_budget / DEFAULT_TIME_BUDGET)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        d["branch_hidden"] = None if self.branch_hidden is None else list(self.branch_hidden)
        return d
