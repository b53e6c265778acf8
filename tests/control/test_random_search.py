"""Random search over a policy's weights (``control.random_search``): the batched network, ARS's step
and its settings; trainings through the emulator are in ``test_reward_policy``."""

from __future__ import annotations

import pytest
import torch

from neuroanimator.control.random_search import (
    RandomSearch,
    ars_update,
    batched_forward,
    flat_weights,
    perturbations,
    set_weights,
)
from neuroanimator.control.reward_policy import RewardSettings, mlp


def test_the_batched_network_is_the_network_under_each_set_of_weights() -> None:
    torch.manual_seed(0)
    net = mlp(5, (7, 6), 3)
    weights = torch.randn(4, flat_weights(net).numel())
    x = torch.randn(4, 9, 5)
    got = batched_forward(net, weights, x)
    assert got.shape == (4, 9, 3)
    for k in range(4):
        set_weights(net, weights[k])
        with torch.no_grad():
            torch.testing.assert_close(got[k], net(x[k]), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="weights for a network of"):
        batched_forward(net, weights[:, :-1], x)


def test_random_search_climbs_a_return_and_stands_still_where_every_policy_earns_the_same() -> None:
    gen = torch.Generator().manual_seed(1)
    how = RandomSearch(directions=8, top=4, step=0.05, noise=0.1)
    slope = torch.randn(20, generator=gen)
    theta = torch.zeros(20)
    for _ in range(50):
        deltas, tried = perturbations(theta, how, gen)
        torch.testing.assert_close(
            tried[:8] - theta, theta - tried[8:], rtol=0, atol=1e-5
        )  # each direction both ways
        earned = tried @ slope
        theta = ars_update(theta, deltas, earned[:8], earned[8:], how)
    # it went up the return's slope, and most of the way along it
    assert float(theta @ slope) > 0
    assert float(torch.nn.functional.cosine_similarity(theta, slope, dim=0)) > 0.8
    deltas, tried = perturbations(theta, how, gen)
    flat = torch.ones(8)
    assert torch.equal(ars_update(theta, deltas, flat, flat, how), theta)


@pytest.mark.parametrize(
    ("make", "says"),
    [
        (lambda: RandomSearch(directions=8, top=9), "top <= directions"),
        (lambda: RandomSearch(episodes=0), "at least one start"),
        (lambda: RandomSearch(noise=0.0), "positive"),
        (lambda: RandomSearch(on="mujoco", stay_inside=True), "only on the emulator"),
        (lambda: RewardSettings(random_search="on"), "random_search is settings"),
    ],
)
def test_random_search_settings_out_of_range_are_refused(make: object, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        make()  # type: ignore[operator]
