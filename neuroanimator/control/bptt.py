"""Backpropagation through time (thesis 5.3-5.4): the objective and its gradient with respect to
the control points, by autograd through the unrolled torch emulator.

The emulator is the artifact's own weights in the form of its ONNX graph: the structured
emulator's transforms around the core with the normalisation folded into the first and last
layers (``export.fold_normalization``), which is the exported step and about twice as fast as the
unfolded module on a batch of one. Its weights are frozen: only the controls get gradients.

Controls are optimised in *normalised* units: ``u = c + h·z`` with ``c`` and ``h`` the centre and
half-width of each control's useful range, so one learning rate suits a 0..32 N main jet and a
±1 attitude jet alike, and ``z = 0`` is the middle of the range. Limits are enforced by projection:
after every update the points are clipped to the actuators' hard limits (``ctrlrange``), and the
held values, which a Catmull-Rom curve can overshoot between points, are clamped to them too,
exactly as MuJoCo clamps a limited actuator's control.

Shapes: B batch of controllers, M points per control, U controls, K super-steps, S state.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.control.objectives import Objective, control_scale
from neuroanimator.control.replay import simulate_held
from neuroanimator.control.splines import ControlSpline
from neuroanimator.core.manifest import Manifest
from neuroanimator.emulator.folding import fold_normalization
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.export.stacked import StackedStep, stackable
from neuroanimator.goals.spec import JobSpec, num_points
from neuroanimator.sim.model import PhysicalModel

FloatArray = NDArray[np.float64]


class FastStep(nn.Module):
    """One emulator super-step, ``(state (B,S), controls (B,U)) -> (B,S)``: the exported graph's form."""

    def __init__(self, emu: StructuredEmulator) -> None:
        super().__init__()
        self.emu = emu
        self.core = fold_normalization(emu)
        self.requires_grad_(False)
        self.num_forces = emu.num_forces

    def forward(self, state: Tensor, controls: Tensor) -> Tensor:
        emu = self.emu
        forces = torch.zeros(state.shape[0], self.num_forces, dtype=state.dtype) if self.num_forces else None
        frame = emu.local_frame(state)  # once per step, shared by T'_x and T'_y
        cols = emu.local_inputs(state, controls, forces, frame, place=False)
        nxt = emu.apply_delta(state, self.core(cols), frame)
        return nxt if emu.regularizer is None else emu.regularizer(nxt, controls)


class FrozenStep(nn.Module):
    """A hierarchical emulator's super-step (global network, local networks, regulariser), frozen:
    ``(state (B,S), controls (B,U)) -> (B,S)``, the same composition as its ONNX graph and in the
    same form: the parts' networks stacked (``hierarchy_export.StackedStep``), which makes a rollout
    and its backward pass through the dolphin's whole hierarchy about 7× faster than part by part."""

    def __init__(self, emu: HierarchicalEmulator) -> None:
        super().__init__()
        self.emu = emu.eval()  # its maps (frames, parts) for whoever reads the trajectory
        self.step: nn.Module = StackedStep(emu) if stackable(emu) else self.emu
        self.requires_grad_(False)

    def forward(self, state: Tensor, controls: Tensor) -> Tensor:
        out: Tensor = self.step(state, controls)
        return out


class GlobalStep(nn.Module):
    """A hierarchical emulator's global network alone (thesis 4.4, 5.3.2), as a step on states:
    ``(state (B,S), controls (B,U)) -> (B,S)`` whose frames (``state @ F``, F (S, K·Q)) are the
    global network's prediction and whose part outside the frames is the state's own.

    The next state is ``s + (f' − s F) F⁺`` with F⁺ the pseudo-inverse of F: its frames are f'
    (exactly when the frames are independent; where two parts share an axis, as the dolphin's fluke
    and last segment share their up axis, the nearest frames that a state can have: the two
    predictions averaged), and what F does not see (the shape of each part in its frame) is carried
    unchanged. An objective that depends on the state only through the frames (as
    ``ControlProblem`` checks) gets the same value and gradient as on a rollout of the frames alone,
    at the cost of one network instead of 1 + K.
    """

    _frames: Tensor  # (S, K·Q)
    _inverse: Tensor  # (K·Q, S)
    _null: Tensor  # (S, S) float64

    def __init__(self, emu: HierarchicalEmulator, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.emu = emu.eval()
        frames = emu.frame_map.double()  # (S, K·Q)
        inverse = torch.linalg.pinv(frames)
        self.register_buffer("_frames", frames.to(dtype), persistent=False)
        self.register_buffer("_inverse", inverse.to(dtype), persistent=False)
        # in float64 whatever the step's dtype: in float32 its rounding alone moved the dolphin's
        # objective by more than the 1e-6 that ``ControlProblem`` tests it to
        null = torch.eye(frames.shape[0], dtype=torch.float64) - frames @ inverse
        self.register_buffer("_null", null, persistent=False)
        self.requires_grad_(False)

    def null_space(self) -> Tensor:
        """(S, S) float64, the projection onto the states' part that no frame sees: ``I − F F⁺``."""
        return self._null

    def forward(self, state: Tensor, controls: Tensor) -> Tensor:
        nxt = self.emu.global_step(state, controls)  # (B, K·Q)
        return state + (nxt - state @ self._frames) @ self._inverse


class ControlProblem:
    """A job's objective as a function of its normalised control points ``z`` (M, U).

    ``value_and_grad(z)`` runs the emulator forward over the horizon and back, returning J, ∇_z J and
    the trajectory; ``evaluate(z)`` scores a batch (B, M, U) without gradients.
    """

    def __init__(
        self,
        emu: StructuredEmulator | HierarchicalEmulator,
        spec: JobSpec,
        manifest: Manifest,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.spec = spec
        self.dtype = dtype  # float64 (with a float64 emulator) for finite-difference checks
        self.step: nn.Module = FrozenStep(emu) if isinstance(emu, HierarchicalEmulator) else FastStep(emu)
        self.horizon = spec.horizon
        self.super_dt = manifest.super_timestep
        self.num_controls = manifest.num_controls
        self.num_points = num_points(self.horizon, spec.points_per_step)
        self.spline = ControlSpline(self.horizon, self.num_points, self.super_dt, dtype)
        useful = np.array([[c.low, c.high] for c in manifest.controls], dtype=np.float64)  # (U, 2)
        limits = np.array([[c.limit_low, c.limit_high] for c in manifest.controls], dtype=np.float64)
        self.centre = 0.5 * (useful[:, 0] + useful[:, 1])
        self.half = np.maximum(0.5 * (useful[:, 1] - useful[:, 0]), 1e-9)
        self.limits = limits
        self.z_low = (limits[:, 0] - self.centre) / self.half  # (U,) ±inf where unlimited
        self.z_high = (limits[:, 1] - self.centre) / self.half
        self._centre = torch.tensor(self.centre, dtype=dtype)
        self._half = torch.tensor(self.half, dtype=dtype)
        self._low = torch.tensor(limits[:, 0], dtype=dtype)
        self._high = torch.tensor(limits[:, 1], dtype=dtype)
        self.objective = Objective(spec, manifest.layout, control_scale(useful))
        self.s0 = torch.tensor(spec.initial_state, dtype=dtype)
        # per-step additive correction (K, S) learned from a MuJoCo replay (``set_correction``)
        self.correction: Tensor | None = None
        self._residuals: int | None = None  # R, the length of ``objective.residuals``
        # the step that gradients (and the search's evaluations) go through: a hierarchy's global
        # network alone where the objective and the criterion depend only on the parts' frames
        # (thesis 4.4, 5.3.2); the full step gives the trajectory that a job returns
        self.gradient_step: nn.Module = self.step
        self.networks = "all"
        if isinstance(emu, HierarchicalEmulator):
            global_only = GlobalStep(emu, dtype)
            if self._depends_only_on_frames(global_only, manifest.state_labels):
                self.gradient_step, self.networks = global_only, "global"

    @torch.no_grad()
    def _depends_only_on_frames(self, global_only: GlobalStep, labels: list[str]) -> bool:
        """Whether the objective and the success checks are unchanged by any change of the states
        that leaves every frame as it is (``null`` (S, S) projects onto such changes).

        The checks read variables, so each must be seen by the frames alone (its column of ``null``
        zero); the objective is probed on the initial controller's rollout (by the global network, the
        cheap one) with random such changes as large as the states themselves."""
        tol = 1e-6
        null = global_only.null_space()
        for check in self.spec.success:
            cols = [labels.index(v) for v in check.variables]
            if float(null[:, cols].abs().max()) > tol:
                return False
        z = torch.as_tensor(self.initial_points()[None], dtype=self.dtype)
        rolled, held = self.rollout(z, global_only)
        states, u = rolled.double(), held.double()
        j = self.objective(states, u)
        gen = torch.Generator().manual_seed(0)
        scale = 1.0 + states.abs().amax(dim=1, keepdim=True)
        for _ in range(3):
            moved = states + (torch.randn(states.shape, generator=gen, dtype=torch.float64) * scale) @ null
            if not torch.allclose(self.objective(moved, u), j, rtol=tol, atol=tol):
                return False
        return True

    # ------------------------------------------------------------------ parametrisation
    def initial_points(self) -> FloatArray:
        """(M, U) normalised points of the job's constant initial controls."""
        u0 = np.asarray(self.spec.initial_controls, dtype=np.float64)
        z = np.repeat(((u0 - self.centre) / self.half)[None, :], self.num_points, axis=0)
        return self.project(z)

    def project(self, z: FloatArray) -> FloatArray:
        """Clip normalised points (..., M, U) to the hard control limits."""
        return np.clip(z, self.z_low, self.z_high)

    def to_physical(self, z: FloatArray) -> FloatArray:
        """Control points in the controls' own units, (..., M, U)."""
        return self.centre + self.half * np.asarray(z, dtype=np.float64)

    def held(self, z: Tensor) -> Tensor:
        """Held physical controls (B, K, U) of normalised points (B, M, U), clamped to the limits."""
        u = self._centre + self._half * self.spline.held(z)
        return torch.maximum(torch.minimum(u, self._high), self._low)

    # ------------------------------------------------------------------ rollout and objective
    def rollout(self, z: Tensor, step: nn.Module | None = None) -> tuple[Tensor, Tensor]:
        """Normalised points (B, M, U) -> states (B, K+1, S) from the initial state, held controls (B, K, U),
        by the emulator's full step or ``step``."""
        step = self.step if step is None else step
        u = self.held(z)
        s = self.s0.expand(z.shape[0], -1)
        states = [s]
        # unbind, not u[:, k]: one backward node for all steps instead of a zero-filled (B, K, U)
        # gradient buffer per step
        for k, u_k in enumerate(u.unbind(dim=1)):
            s = step(s, u_k)
            if self.correction is not None:
                s = s + self.correction[k]
            states.append(s)
        return torch.stack(states, dim=1), u

    def value_and_grad(self, z: FloatArray) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        """J, ∇_z J (M, U), states (K+1, S) and held controls (K, U) of one controller ``z`` (M, U)."""
        zt = torch.tensor(np.asarray(z)[None], dtype=self.dtype, requires_grad=True)
        states, u = self.rollout(zt, self.gradient_step)
        j = self.objective(states.double(), u.double())[0]
        j.backward()
        assert zt.grad is not None
        grad = zt.grad[0].double().numpy()
        return float(j.detach()), grad, states[0].detach().double().numpy(), u[0].detach().double().numpy()

    def values_and_grads(self, zs: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """J (B,), ∇_z J (B, M, U), states (B, K+1, S) and held controls (B, K, U) of a batch of
        controllers (B, M, U), in one batched rollout and one backward pass (the controllers are
        independent, so the gradient of the sum is each one's own gradient)."""
        zt = torch.tensor(np.asarray(zs), dtype=self.dtype, requires_grad=True)
        states, u = self.rollout(zt, self.gradient_step)
        j = self.objective(states.double(), u.double())
        j.sum().backward()
        assert zt.grad is not None
        return (
            j.detach().numpy(),
            zt.grad.double().numpy(),
            states.detach().double().numpy(),
            u.detach().double().numpy(),
        )

    def residual_jacobian(
        self, z: FloatArray
    ) -> tuple[float, FloatArray, FloatArray, FloatArray, tuple[FloatArray, FloatArray]]:
        """J, ∇_z J (M, U), the residuals r (R,) of ``Objective.residuals``, their Jacobian (R, M·U)
        and (states (K+1, S), held controls (K, U)) of one controller ``z`` (M, U).

        One batched rollout of R + 1 copies of ``z`` and one backward pass: the copies are
        independent, so the gradient of Σᵢ rᵢ(copy i) + J(copy R) holds ∇rᵢ in row i and ∇J in row R.
        """
        zs = np.repeat(np.asarray(z, dtype=np.float64)[None], self._residual_count(z) + 1, axis=0)
        zt = torch.tensor(zs, dtype=self.dtype, requires_grad=True)
        states, u = self.rollout(zt, self.gradient_step)
        r_all = self.objective.residuals(states[:-1].double(), u[:-1].double())  # (R, R)
        j = self.objective(states[-1:].double(), u[-1:].double())[0]
        (r_all.diagonal().sum() + j).backward()
        assert zt.grad is not None
        grad = zt.grad.double().numpy()
        return (
            float(j.detach()),
            grad[-1],
            r_all[0].detach().numpy(),
            grad[:-1].reshape(grad.shape[0] - 1, -1),
            (states[-1].detach().double().numpy(), u[-1].detach().double().numpy()),
        )

    def _residual_count(self, z: FloatArray) -> int:
        if self._residuals is None:
            with torch.no_grad():
                states, u = self.rollout(
                    torch.as_tensor(np.asarray(z)[None], dtype=self.dtype), self.gradient_step
                )
                self._residuals = int(self.objective.residuals(states.double(), u.double()).shape[-1])
        return self._residuals

    @torch.no_grad()
    def trajectory(self, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """States (K+1, S) and held controls (K, U) of one controller (M, U), without gradients."""
        states, u = self.rollout(torch.as_tensor(np.asarray(z)[None], dtype=self.dtype))
        return states[0].double().numpy(), u[0].double().numpy()

    @torch.no_grad()
    def score(self, states: FloatArray, held: FloatArray) -> float:
        """J of one trajectory (K+1, S) under held controls (K, U), e.g. a MuJoCo replay."""
        return float(self.objective(torch.from_numpy(states[None]), torch.from_numpy(held[None]))[0])

    @torch.no_grad()
    def set_correction(self, physical_states: FloatArray | None, held: FloatArray | None = None) -> None:
        """Correct the emulator along a physical trajectory (K+1, S) driven by held controls (K, U).

        Each step gets the additive term ``c_k = s_phys[k+1] − N(s_phys[k], u_k)``, so the corrected
        emulator, driven by the same controls, reproduces the physical trajectory exactly and its
        gradients are the emulator's along it (time-indexed bias correction, as in Abbeel, Quigley and
        Ng 2006, "Using inaccurate models in reinforcement learning"). ``None`` removes it.
        """
        if physical_states is None or held is None:
            self.correction = None
            return
        phys = torch.as_tensor(np.asarray(physical_states), dtype=self.dtype)
        u = torch.as_tensor(np.asarray(held), dtype=self.dtype)
        self.correction = phys[1:] - self.gradient_step(phys[:-1], u)

    @torch.no_grad()
    def evaluate_physics(self, physical: PhysicalModel, z: FloatArray, threads: int = 1) -> FloatArray:
        """J of a batch of controllers (B, M, U) on MuJoCo: the same held controls, each held for its
        n physical steps from the same initial state, scored by the same objective, (B,)."""
        held = self.held(torch.as_tensor(np.asarray(z), dtype=self.dtype)).double().numpy()
        s0 = np.asarray(self.spec.initial_state, dtype=np.float64)[None]
        states = simulate_held(physical, s0, held, self.spec.substeps, threads=threads)
        return self.objective(torch.from_numpy(states), torch.from_numpy(held)).numpy()

    @torch.no_grad()
    def evaluate(self, z: FloatArray) -> FloatArray:
        """J of a batch of controllers (B, M, U) on the emulator, (B,)."""
        zt = torch.as_tensor(np.asarray(z), dtype=self.dtype)
        states, u = self.rollout(zt, self.gradient_step)
        return self.objective(states.double(), u.double()).numpy()
