"""The policy-driven rows of a state pool, and their controls in a batched tick.

``PolicyColumns`` sits beside a ``StatePool``'s arrays, one row per slot: ``index`` (capacity,) the
policy driving the slot (an index into ``policies``; -1: none), ``goals`` (capacity, G) its goal (G:
the widest goal of the pool's policies), ``goal_step`` (capacity,) the slot's step count when its goal
was set, and ``applied`` (capacity, U) the controls its policy chose for its last super-step.

``PolicyTick`` is one batch's share of them: ``plan`` gathers, on the event loop, the policy rows of
a batch grouped by policy; ``apply`` (which may run in a worker thread with the emulator's call)
evaluates each policy ONCE over all its rows and writes the controls into the batch's inputs;
``record`` writes them back to ``applied`` on the event loop.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.emulator.policies import LoadedPolicy

log = logging.getLogger(__name__)


class PolicyColumns:
    """Per-slot policy columns of one pool (module doc)."""

    def __init__(self, capacity: int, num_controls: int) -> None:
        self.index = np.full(capacity, -1, np.int32)
        self.goals = np.zeros((capacity, 0), np.float32)
        self.goal_step = np.zeros(capacity, np.int64)
        self.applied = np.zeros((capacity, num_controls), np.float32)
        self.policies: list[LoadedPolicy] = []
        self.count = 0  # slots driven by a policy: a pool without any skips the policy step at once

    def grow(self, capacity: int) -> None:
        old = len(self.index)
        for name in ("index", "goals", "goal_step", "applied"):
            arr = getattr(self, name)
            grown = np.zeros((capacity, *arr.shape[1:]), arr.dtype)
            grown[:old] = arr
            if name == "index":
                grown[old:] = -1
            setattr(self, name, grown)

    def attach(self, slot: int, policy: LoadedPolicy, goal: NDArray[np.float32], step: int) -> None:
        if policy not in self.policies:
            self.policies.append(policy)
        g = policy.goal_size
        if g > self.goals.shape[1]:  # a policy with a wider goal than any before: widen the columns
            wider = np.zeros((len(self.index), g), np.float32)
            wider[:, : self.goals.shape[1]] = self.goals
            self.goals = wider
        if self.index[slot] < 0:
            self.count += 1
        self.index[slot] = self.policies.index(policy)
        self.set_goal(slot, goal, step)
        self.applied[slot] = 0.0

    def set_goal(self, slot: int, goal: NDArray[np.float32], step: int) -> None:
        self.goals[slot, : len(goal)] = goal
        self.goal_step[slot] = step

    def detach(self, slot: int) -> None:
        if self.index[slot] >= 0:
            self.count -= 1
            self.index[slot] = -1


Rows = NDArray[np.intp] | slice
"""Rows of a batch: indices, or ``slice(None)`` when a policy drives every row (no gather then)."""
EVERY_ROW = slice(None)


@dataclass
class _Group:
    """The rows of one batch driven by one policy: (K,) row indices into the batch (or every row),
    (K, G) goals, (K,) steps since each goal was set, and after ``apply`` the (K, U) controls."""

    policy: LoadedPolicy
    rows: Rows
    goals: NDArray[np.float32]
    since: NDArray[np.int64]
    controls: NDArray[np.float32] | None = None


class PolicyTick:
    """The policy-driven rows of one batch and the controls their policies chose (module doc)."""

    def __init__(self, slots: NDArray[np.intp], groups: list[_Group]) -> None:
        self.slots = slots
        self.groups = groups
        self.bad: NDArray[np.bool_] | None = None  # (B,) rows whose policy gave non-finite controls

    @classmethod
    def plan(
        cls, cols: PolicyColumns, steps: NDArray[np.int64], slots: NDArray[np.intp]
    ) -> PolicyTick | None:
        """The policy rows among the batch's (B,) ``slots`` (``steps``: the pool's step counts), grouped
        by policy; None when no row is driven by one (the one comparison an undriven batch costs)."""
        if not cols.count:
            return None
        which = cols.index[slots]
        first = int(which[0])
        if first >= 0 and (len(which) == 1 or (which == first).all()):  # the usual tick: one group
            policy = cols.policies[first]
            goals = np.take(cols.goals, slots, axis=0)  # (a row gather: far cheaper than [slots, :g])
            if goals.shape[1] != policy.goal_size:
                goals = np.ascontiguousarray(goals[:, : policy.goal_size])
            return cls(slots, [_Group(policy, EVERY_ROW, goals, steps[slots] - cols.goal_step[slots])])
        driven = which >= 0
        if not driven.any():
            return None
        groups = []
        for k in np.unique(which[driven]).tolist():
            rows = np.flatnonzero(which == k)
            policy = cols.policies[k]
            mine = slots[rows]
            goals = cols.goals[mine, : policy.goal_size]
            groups.append(_Group(policy, rows, goals, steps[mine] - cols.goal_step[mine]))
        return cls(slots, groups)

    def apply(
        self,
        states: NDArray[np.float32],
        inputs: NDArray[np.float32],
        low: NDArray[np.float32],
        high: NDArray[np.float32],
    ) -> None:
        """Each policy once over its rows of the batch's states (B, S): the controls, clipped to the
        emulator's trained range (``low``, ``high`` (U,)), replace those rows' first U inputs of
        (B, U+F) in place. A row whose controls are not finite is marked in ``bad``."""
        nu = len(low)
        for g in self.groups:
            u = g.policy.controls(states if g.rows is EVERY_ROW else states[g.rows], g.goals, g.since)
            if not np.isfinite(u).all():  # (rare: one flat test first)
                if self.bad is None:
                    self.bad = np.zeros(len(states), bool)
                self.bad[np.arange(len(states))[g.rows][~np.isfinite(u).all(axis=1)]] = True
            # (a policy whose graph keeps its controls in the range needs no clip: a pass spared)
            g.controls = u if g.policy.keeps_within(low, high) else np.clip(u, low, high, out=u)
            inputs[g.rows, :nu] = u

    def sole_policy(self) -> LoadedPolicy | None:
        """The policy when it drives every row of the batch (the usual tick), else None."""
        if len(self.groups) == 1 and self.groups[0].rows is EVERY_ROW:
            return self.groups[0].policy
        return None

    def took(self, controls: NDArray[np.float32]) -> None:
        """The (B, U) controls the sole policy chose in a call composed with the emulator's (already
        clipped there): kept for ``record`` as ``apply`` keeps them, non-finite rows marked ``bad``."""
        g = self.groups[0]
        g.policy.calls += 1
        if not np.isfinite(controls).all():  # (rare: one flat test first)
            self.bad = np.logical_not(np.isfinite(controls).all(axis=1))
        g.controls = controls

    def record(self, cols: PolicyColumns) -> None:
        """The chosen controls into ``applied`` (on the event loop: the pool may have grown meanwhile)."""
        for g in self.groups:
            if g.controls is not None:
                cols.applied[self.slots[g.rows]] = g.controls
        if self.bad is not None:
            log.warning(
                "a policy gave non-finite controls for %d sessions: they diverge",
                int(self.bad.sum()),
                extra={"policies": [g.policy.label for g in self.groups]},
            )
