"""The super-step chosen from the motion for any model: probes wherever the longest misses the bar,
limits counted anywhere within a super-step, a body that turns a full turn within one left out, and
an emulator trimmed at its operating point."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from neuroanimator import catalog
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.training.motion import MAX_TURN, FastestMotion, bound_super_steps
from neuroanimator.training.super_step import choose_substeps, constraint_activity
from neuroanimator.training.train import train

DATA = Path(__file__).resolve().parent / "data"


def test_a_cart_driven_into_its_rails_limits_engages_them_within_super_steps() -> None:
    """Gymnasium's cart with a double pendulum: its slider motor drives the cart into the rail's limits,
    mostly between the instants a super-step starts at."""
    model = load_mjcf(
        DATA / "inverted_double_pendulum", entry="inverted_double_pendulum.xml", stabilise=False
    )
    within = constraint_activity(model)
    at_starts = constraint_activity(model, window=1)
    assert within.contact == 0 and within.limit > at_starts.limit > 0


def test_a_smooth_model_is_probed_and_gets_the_longest_step_its_probe_learns() -> None:
    """No contact and no limit no longer skips the probes: the longest is probed, and taken when its
    short probe reaches the bar."""
    model = catalog.get("pendulum-active")
    cfg = TrainConfig(examples=2000, max_epochs=20, progress=False, seed=0)
    choice = choose_substeps(model, cfg, candidates=(10, 5))
    assert choice.probes and 10 in choice.probes and "probe one-step errors" in choice.reason
    assert choice.substeps == 10 if choice.probes[10] <= 0.1 else choice.substeps == 5


def test_a_body_that_turns_a_full_turn_within_a_super_step_is_not_emulated_at_it() -> None:
    model = load_mjcf(DATA / "skydio_x2", entry="x2.xml", stabilise=False)
    dt = model.dt
    times = np.arange(10, dtype=np.float64) * 0.1
    fast = FastestMotion(
        times,
        np.full(10, 1.5 * MAX_TURN / (50 * dt), dtype=np.float64),
        np.full(10, 20.0, dtype=np.float64),
        "joint0.angvel",
    )
    allowed, why = bound_super_steps(model, (50, 25, 10), fast)
    assert allowed == (25, 10) and why is not None and "n=50 left out" in why
    slow = FastestMotion(
        times,
        np.full(10, 0.5 * MAX_TURN / (50 * dt), dtype=np.float64),
        np.full(10, 20.0, dtype=np.float64),
        "joint0.angvel",
    )
    assert bound_super_steps(model, (50, 25, 10), slow) == ((50, 25, 10), None)


def test_an_emulator_is_trimmed_at_its_operating_point() -> None:
    """A short training of the X2: at its hover keyframe, held at its hover thrusts, the emulated step is
    MuJoCo's (the drone stays put), whatever the rest of its error."""
    model = load_mjcf(DATA / "skydio_x2", entry="x2.xml")
    cfg = TrainConfig(
        substeps=25, examples=3000, test_examples=500, max_epochs=5, progress=False, rollout_steps=0
    )
    result = train(model, cfg)
    before, after = result.metrics["operating_residual"]
    assert after < 1e-5 < before
    op = model.spec.operating
    assert op is not None
    hover = torch.tensor(model.spec.initial.centres, dtype=torch.float32)
    thrust = torch.tensor(op.control_centres, dtype=torch.float32)
    state = hover
    with torch.no_grad():
        for _ in range(8):  # 2 s
            state = result.emulator(state, thrust)
    assert float((state[0, :3] - hover[0, :3]).norm()) < 1e-3


def test_a_model_without_contact_keeps_the_longest_step_its_probe_nearly_learns() -> None:
    """dm_control's cartpole probed 0.055, 0.034 and 0.0079 at n = 50, 25 and 10, and trains to 0.0007 at
    n = 50, the acrobot 0.0726 and 0.0014: where no contact engages, a probe overstates the error more.
    Gymnasium's double pendulum, driven into its rail's limits, needs the shortest."""
    from neuroanimator.training.super_step import PROBE_SLACK, SMOOTH_PROBE_SLACK, pick

    probes = {50: 0.055, 25: 0.034, 10: 0.0079}
    assert pick(probes)[0] == 25
    assert pick(probes, PROBE_SLACK * SMOOTH_PROBE_SLACK)[0] == 50
    assert pick({50: 0.0726, 25: 0.02}, PROBE_SLACK * SMOOTH_PROBE_SLACK)[0] == 50
    assert pick({50: 0.305, 25: 0.186, 10: 0.0744}, PROBE_SLACK * SMOOTH_PROBE_SLACK)[0] == 10
