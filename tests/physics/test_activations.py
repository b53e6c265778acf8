"""Actuators with their own dynamics (a filter, an integrator, a muscle) hold activations in MuJoCo's
``act``: the next state depends on them, so a user's model keeps them in its state (``<actuator>.act``
groups), and a run stepped one super-step at a time from the states it passes through is the run
simulated in one go."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neuroanimator.core.state import StateGroup
from neuroanimator.sim import mjcf
from neuroanimator.sim.model import PhysicalModel

FILTERED = """
<mujoco model="filtered">
  <option timestep="0.005"/>
  <worldbody>
    <body name="arm">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="1"/>
      <body name="forearm" pos="0.4 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <general name="slow" joint="shoulder" dyntype="filter" dynprm="0.3" gainprm="4" ctrlrange="-1 1"/>
    <motor name="direct" joint="elbow" ctrlrange="-2 2"/>
    <general name="integrating" joint="elbow" dyntype="integrator" gainprm="1" ctrlrange="-1 1"
             actlimited="true" actrange="-0.5 0.5"/>
  </actuator>
</mujoco>
"""


@pytest.fixture
def filtered(tmp_path: Path) -> PhysicalModel:
    path = tmp_path / "filtered.xml"
    path.write_text(FILTERED)
    return mjcf.load_mjcf(path, stabilise=False)


def test_activations_are_state(filtered: PhysicalModel) -> None:
    acts = [g for g in filtered.layout if g.source == "act"]
    assert [g.name for g in acts] == ["slow.act", "integrating.act"]
    assert [g.address for g in acts] == [0, 1]
    assert StateGroup.model_validate(acts[0].model_dump()) == acts[0]  # the contract carries them
    state = filtered.initial_states(np.random.default_rng(0), 64)
    slow = state[:, filtered.layout.slice_of("slow.act")]
    assert slow.min() >= -1.0 and slow.max() <= 1.0 and slow.std() > 0.3  # spread over the control range
    full = filtered.to_physics(state)
    assert np.array_equal(filtered.from_physics(full), state)


def test_a_run_stepped_super_step_by_super_step_is_the_run(filtered: PhysicalModel) -> None:
    rng = np.random.default_rng(1)
    s0 = filtered.initial_states(rng, 8)
    n, k = 20, 5
    held = rng.uniform(
        filtered.control_range[:, 0], filtered.control_range[:, 1], (8, k, filtered.num_controls)
    )
    whole = filtered.simulate(s0, np.repeat(held, n, axis=1), None, nstep=n * k)[:, n - 1 :: n]
    s = s0
    for i in range(k):
        s = filtered.step_held(s, held[:, i], None, n)
        np.testing.assert_allclose(s, whole[:, i], rtol=1e-9, atol=1e-9)
    # and the activations matter: the same run from zero activations ends elsewhere
    zeroed = s0.copy()
    zeroed[:, filtered.layout.slice_of("slow.act")] = 0.0
    other = filtered.step_held(zeroed, held[:, 0], None, n)
    assert np.abs(other - whole[:, 0]).max() > 1e-3
