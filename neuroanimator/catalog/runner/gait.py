"""A running controller for the runner, after Hodgins (1995) and Raibert: a state machine per leg
(stance, flight, swing), servo targets at the joints, foot placement from the forward speed, and
torso attitude held by the stance hip.

Every run of a batch has its own state machine; the controller works on arrays of runs at once, so
data generation steps many runs together: ``run`` hands ``mujoco.rollout`` ``control_every`` physical
steps at a time with the controls held, then asks the controller for the next ones.

The cycle of one stride: stance on one leg (``stance_s`` seconds), flight (until the other foot
touches, ``flight_max_s`` at most), stance on the other leg, flight. In stance the leg's hip servo
holds the pelvis upright (pitch, roll and heading); its knee gives a little and extends to push off
with the ankle. The other leg swings: knee folded, thigh brought to the angle that puts the foot at
``x = v·stance_s/2 + k_v·(v − v_target)`` ahead of the centre of mass at touchdown (Raibert's rule),
and sideways against the sideways speed. Before touchdown its knee extends.

Shapes: B = runs, U = 29 controls (servo targets, ``runner.JOINTS``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import mujoco
import numpy as np
from mujoco import rollout
from numpy.typing import NDArray

from neuroanimator.catalog.runner import body

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

FloatArray = NDArray[np.float64]
_Placement = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
"""A foot's side sign (B,) -> thigh angles (forward, sideways), each (B,), that place the foot."""

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_XFRC_APPLIED
STANCE, FLIGHT = 0, 1
BODY_WEIGHT = 70.0 * 9.81  # newtons


@dataclass(frozen=True)
class Gait:
    """The controller's parameters (radians, seconds, metres; torques in N·m per radian). The defaults
    come from ``python bench/runner_tune.py --batch 24 --starts 3 --speeds 2.0,1.7,2.4 --seconds 15
    --rounds 16 --control-every 6 --kinematic --budget-s 1800``, started from the gait before: a gait
    scored by how reliably it stays up from perturbed starts and under pushes, with the controller
    every 6 physical steps reading ``KinematicSensors`` (as it does on the emulator)."""

    stance_s: float = 0.2067
    flight_max_s: float = 0.0269
    lean: float = -0.0964  # forward lean of the pelvis while running
    lean_per_speed: float = 0.0619  # extra lean per m/s below the target speed
    pitch_kp: float = 942.0966
    pitch_kd: float = 114.5087
    roll_kp: float = 1626.6317
    roll_kd: float = 189.0626
    yaw_kp: float = 75.1294
    yaw_kd: float = 69.575
    leg_length: float = 0.88
    step_gain: float = 0.8585  # foot ahead of the centre of mass: step_gain·v·stance_s
    speed_gain: float = 0.0971  # ... plus speed_gain·(v − v_target)
    side_gain: float = 0.1611  # sideways placement per m/s of sideways speed
    width: float = 0.0004  # nominal sideways foot offset from the centre of mass
    swing_knee: float = 1.7102
    fold_fraction: float = 0.8285  # fraction of the other leg's stance the swing knee stays folded
    touchdown_knee: float = 0.4735
    stance_knee: float = 0.4969
    pushoff_knee: float = 0.3886
    pushoff_ankle: float = -0.4352
    pushoff_from: float = 0.3471  # fraction of stance after which the leg pushes off
    liftoff_hip: float = 0.8756  # world thigh angle the leaving leg swings towards
    arm_swing: float = 1.2297
    elbow: float = 1.5
    waist_lean: float = 0.2713


@dataclass(frozen=True)
class Push:
    """A push of the torso: ``force`` newtons (world x, y, z; or (B, 3), one per run) from ``start_s``
    seconds (or (B,), one per run) for ``duration_s``."""

    force: tuple[float, float, float] | FloatArray = (0.0, 250.0, 0.0)
    start_s: float | FloatArray = 10.0
    duration_s: float = 0.2

    def active(self, now: float, batch: int) -> NDArray[np.bool_]:
        """(B,) which runs are being pushed at time ``now`` (seconds)."""
        start = np.broadcast_to(np.asarray(self.start_s, float), (batch,))
        return (start <= now) & (now < start + self.duration_s)


def _quat_to_mat(q: FloatArray) -> FloatArray:
    """(B, 4) unit quaternions (w, x, y, z) -> (B, 3, 3) rotation matrices."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


@dataclass
class Attitude:
    """The pelvis in its heading frame: (B,) angles and rates; ``heading`` is the yaw."""

    pitch: FloatArray
    roll: FloatArray
    heading: FloatArray
    pitch_rate: FloatArray
    roll_rate: FloatArray
    yaw_rate: FloatArray
    velocity: FloatArray  # (B, 2) centre-of-mass velocity, forward and leftward in the heading frame

    @classmethod
    def of(cls, qpos: FloatArray, qvel: FloatArray, com_vel: FloatArray) -> Attitude:
        r = _quat_to_mat(qpos[:, 3:7])
        heading = np.arctan2(r[:, 1, 0], r[:, 0, 0])
        c, s = np.cos(heading), np.sin(heading)

        def to_heading(v: FloatArray) -> FloatArray:
            return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)

        up = to_heading(r[:, :, 2])
        omega = to_heading(np.einsum("bij,bj->bi", r, qvel[:, 3:6]))
        return cls(
            pitch=np.arctan2(up[:, 0], up[:, 2]),
            roll=np.arctan2(-up[:, 1], up[:, 2]),
            heading=heading,
            pitch_rate=omega[:, 1],
            roll_rate=omega[:, 0],
            yaw_rate=omega[:, 2],
            velocity=to_heading(com_vel)[:, :2],
        )


class RunnerController:
    """The state machine and servo targets of a batch of runners (see the module docstring)."""

    def __init__(self, m: mujoco.MjModel, gait: Gait | None = None) -> None:
        self.m = m
        self.gait = gait or Gait()
        act = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i): i for i in range(m.nu)}
        joints = [int(m.actuator_trnid[act[name], 0]) for name in body.JOINTS]
        self.ctrl_ids = np.array([act[name] for name in body.JOINTS])
        self.qpos_at = m.jnt_qposadr[joints]
        self.dof_at = m.jnt_dofadr[joints]
        self.kp = m.actuator_gainprm[self.ctrl_ids, 0].copy()
        self.kv = -m.actuator_biasprm[self.ctrl_ids, 2].copy()
        self.force_limit = m.actuator_forcerange[self.ctrl_ids, 1].copy()
        self.low = m.actuator_ctrlrange[self.ctrl_ids, 0].copy()
        self.high = m.actuator_ctrlrange[self.ctrl_ids, 1].copy()
        self.index = {name: k for k, name in enumerate(body.JOINTS)}
        self.stand = np.asarray(body.stand_targets())
        sensor = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SENSOR, i): i for i in range(m.nsensor)}
        self.sensor_at = {name: int(m.sensor_adr[i]) for name, i in sensor.items()}
        self.sign = np.array([1.0, -1.0])
        self.stand_gain = (2.0, 0.5)  # abduction and twist axes are mirrored on the right

    # ------------------------------------------------------------------ state machine
    def reset(self, batch: int, target_speed: FloatArray | float, heading: FloatArray | float = 0.0) -> None:
        """Start ``batch`` runs in stance on the left leg; ``target_speed`` 0 means stand still."""
        self.target_speed = np.broadcast_to(np.asarray(target_speed, float), (batch,)).copy()
        self.target_heading = np.broadcast_to(np.asarray(heading, float), (batch,)).copy()
        self.stance_leg = np.zeros(batch, int)
        self.phase = np.full(batch, STANCE)
        self.phase_time = np.zeros(batch)
        self.load = np.ones(batch)

    def feet_touch(self, sensordata: FloatArray) -> FloatArray:
        """(..., nsensordata) -> (..., 2) normal force under the left and right foot (sole and toes), newtons."""
        at = self.sensor_at
        return np.stack(
            [
                sensordata[..., at[f"{side}_sole"]] + sensordata[..., at[f"{side}_toe_pad"]]
                for side in body.SIDES
            ],
            axis=-1,
        )

    def _advance(self, touch: FloatArray, dt: float) -> None:
        """Move each run's state machine on by ``dt``: stance ends after ``stance_s`` on the ground
        (or when the other foot lands after push-off began), flight when the other foot lands."""
        g = self.gait
        runs = np.arange(self.stance_leg.size)
        other = 1 - self.stance_leg
        other_down = touch[runs, other] > 50.0
        in_stance = self.phase == STANCE
        # stance time counts only while the stance foot is on the ground: a late touchdown waits
        self.phase_time += np.where(in_stance & (touch[runs, self.stance_leg] <= 50.0), 0.0, dt)
        to_flight = in_stance & (self.phase_time >= g.stance_s) & ~other_down
        swap = (in_stance & (self.phase_time >= g.pushoff_from * g.stance_s) & other_down) | (
            (self.phase == FLIGHT) & (other_down | (self.phase_time >= g.flight_max_s))
        )
        self.phase[to_flight] = FLIGHT
        self.phase_time[to_flight] = 0.0
        self.stance_leg[swap] = other[swap]
        self.phase[swap] = STANCE
        self.phase_time[swap] = 0.0
        self.running = self.target_speed > 0.0
        # how much the stance foot bears: the hip holds the pelvis only as far as the foot is loaded
        self.load = np.clip(touch[runs, self.stance_leg] / (0.3 * BODY_WEIGHT), 0.0, 1.0)

    # ------------------------------------------------------------------ servo targets
    def act(self, qpos: FloatArray, qvel: FloatArray, sensordata: FloatArray, dt: float) -> FloatArray:
        """(B, nq), (B, nv), (B, nsensordata) -> (B, U) servo targets for the next ``dt`` seconds."""
        self._advance(self.feet_touch(sensordata), dt)
        at = self.sensor_at
        com_vel = sensordata[:, at["com_vel"] : at["com_vel"] + 3]
        att = Attitude.of(qpos, qvel, com_vel)
        heading_error = np.angle(np.exp(1j * (att.heading - self.target_heading)))
        q = qpos[:, self.qpos_at]  # (B, U) the servoed joints' angles and rates, in control order
        qd = qvel[:, self.dof_at]
        # the standing pose, (B, U); each part of the gait writes its joints' targets over it, the
        # stance hip last among the legs since it blends the stance knee's target with touchdown's
        u = np.repeat(self.stand[None], q.shape[0], axis=0)
        pelvis_torque = self._pelvis_torque(att, heading_error)
        placement = self._placement(att.velocity, heading_error)
        swing_hip = self._swing_leg(u, att, placement)
        self._stance_knee_and_ankle(u)
        hip_torque = self._stance_hip_torque(q, qd, pelvis_torque, swing_hip)
        self._stance_hip(u, att, placement, self._holding(q, qd, hip_torque))
        self._arms_and_waist(u, q)
        standing = ~self.running
        if standing.any():
            u[standing] = self._stand(att, standing, sensordata[standing])
        return np.clip(u, self.low, self.high)

    def _col(self, side: int, joint: str) -> int:
        """The column of ``joint`` ("hip_y", "knee", ...) of leg or arm ``side`` (0 left, 1 right) in U."""
        return self.index[f"{body.SIDES[side]}_{joint}"]

    def _cols(self, sides: NDArray[np.int_], joint: str) -> list[int]:
        """(B,) sides -> each run's column of ``joint`` on its side."""
        return [self._col(s, joint) for s in sides]

    def _pelvis_torque(
        self, att: Attitude, heading_error: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(B,) torques the pelvis needs on pitch, roll and heading: PD servos towards upright, the
        heading to run in, and (running) a forward lean that grows when the run is slower than its
        target."""
        g = self.gait
        speed_error = self.target_speed - att.velocity[:, 0]
        lean = np.where(self.running, g.lean + g.lean_per_speed * np.clip(speed_error, -1.0, 1.0), 0.0)
        t_pitch = -g.pitch_kp * (att.pitch - lean) - g.pitch_kd * att.pitch_rate
        t_roll = -g.roll_kp * att.roll - g.roll_kd * att.roll_rate
        t_yaw = -g.yaw_kp * heading_error - g.yaw_kd * att.yaw_rate
        return t_pitch, t_roll, t_yaw

    def _placement(self, velocity: FloatArray, heading_error: FloatArray) -> _Placement:
        """Raibert's foot placement for the (B, 2) forward and leftward velocity in the pelvis'
        heading frame: a function of each run's foot side sign (B,) -> its thigh angles (forward,
        sideways), each (B,), in the pelvis' heading frame."""
        g = self.gait
        v = velocity
        # placement in the frame of the target heading (the way to run), turned into the pelvis'
        # heading frame, so that a turned pelvis does not read its own turn as sideways speed
        ce, se = np.cos(heading_error), np.sin(heading_error)
        v_run = np.stack([ce * v[:, 0] - se * v[:, 1], se * v[:, 0] + ce * v[:, 1]], axis=1)
        reach_run = g.step_gain * v_run[:, 0] * g.stance_s + g.speed_gain * (v_run[:, 0] - self.target_speed)

        def placement(sign: FloatArray) -> tuple[FloatArray, FloatArray]:
            """Thigh angles (forward, sideways) in the pelvis' heading frame for a foot on side ``sign``."""
            lateral_run = sign * g.width + g.side_gain * v_run[:, 1]
            fwd = ce * reach_run + se * lateral_run
            side = -se * reach_run + ce * lateral_run
            return (
                np.arcsin(np.clip(fwd / g.leg_length, -0.8, 0.8)),
                np.arcsin(np.clip(side / g.leg_length, -0.5, 0.5)),
            )

        return placement

    def _swing_leg(
        self, u: FloatArray, att: Attitude, placement: _Placement
    ) -> tuple[FloatArray, FloatArray]:
        """Write the swing leg's targets into ``u`` (B, U): thigh towards the placement (an angle in the
        world), knee folded for most of the other leg's stance, then extended for touchdown. Returns
        the (B,) targets of its hip's flexion and abduction."""
        g = self.gait
        runs = np.arange(u.shape[0])
        swing = 1 - self.stance_leg
        in_stance = self.phase == STANCE
        frac = self.phase_time / g.stance_s
        side_sign = self.sign[swing]
        thigh_fwd, thigh_side = placement(side_sign)
        folded = in_stance & (frac < g.fold_fraction)
        sw_hip_y = thigh_fwd + att.pitch
        sw_hip_x = side_sign * (thigh_side - att.roll)
        sw_knee = np.where(folded, g.swing_knee, g.touchdown_knee)
        u[runs, self._cols(swing, "hip_y")] = sw_hip_y
        u[runs, self._cols(swing, "hip_x")] = sw_hip_x
        u[runs, self._cols(swing, "knee")] = sw_knee
        u[runs, self._cols(swing, "ankle_y")] = 0.2
        return sw_hip_y, sw_hip_x

    def _stance_knee_and_ankle(self, u: FloatArray) -> None:
        """Write the knee and ankle targets of the stance leg (or, in flight, of the leg that just left
        the ground) into ``u`` (B, U): the knee gives, then extends with the ankle to push off."""
        g = self.gait
        runs = np.arange(u.shape[0])
        stance = self.stance_leg
        in_stance = self.phase == STANCE
        frac = self.phase_time / g.stance_s
        st_knee = np.where(
            in_stance, np.where(frac < g.pushoff_from, g.stance_knee, g.pushoff_knee), g.swing_knee
        )
        st_ankle = np.where(in_stance & (frac >= g.pushoff_from), g.pushoff_ankle, 0.0)
        st_ankle = np.where(in_stance, st_ankle, 0.2)
        u[runs, self._cols(stance, "knee")] = st_knee
        u[runs, self._cols(stance, "ankle_y")] = st_ankle

    def _servo_torque(self, q: FloatArray, qd: FloatArray, cols: list[int], target: FloatArray) -> FloatArray:
        """(B,) torque each run's servo at its column ``cols`` applies towards ``target`` (B,), from the
        joint angles ``q`` and rates ``qd`` (B, U), within its force limit."""
        runs = np.arange(q.shape[0])
        c = np.asarray(cols)
        tau = self.kp[c] * (target - q[runs, c]) - self.kv[c] * qd[runs, c]
        return np.asarray(np.clip(tau, -self.force_limit[c], self.force_limit[c]))

    def _hold(self, q: FloatArray, qd: FloatArray, cols: list[int], torque: FloatArray) -> FloatArray:
        """(B,) the servo target at each run's column ``cols`` under which its servo applies ``torque``."""
        runs = np.arange(q.shape[0])
        c = np.asarray(cols)
        return np.asarray(q[runs, c] + (torque + self.kv[c] * qd[runs, c]) / self.kp[c])

    def _stance_hip_torque(
        self,
        q: FloatArray,
        qd: FloatArray,
        pelvis_torque: tuple[FloatArray, FloatArray, FloatArray],
        swing_hip: tuple[FloatArray, FloatArray],
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(B,) torques of the stance hip's flexion, abduction and twist: what the pelvis needs less
        what the swing hip, servoed to ``swing_hip`` (flexion, abduction targets), already applies to
        it (Hodgins; SIMBICON)."""
        t_pitch, t_roll, t_yaw = pelvis_torque
        stance = self.stance_leg
        swing = 1 - stance
        side_sign = self.sign[swing]
        tau_sw_y = self._servo_torque(q, qd, self._cols(swing, "hip_y"), swing_hip[0])
        tau_sw_x = self._servo_torque(q, qd, self._cols(swing, "hip_x"), swing_hip[1])
        # pelvis pitch gets +flexion torque of each hip; roll gets -sign·abduction; yaw -sign·twist
        st_sign = self.sign[stance]
        stance_pitch = t_pitch - tau_sw_y
        stance_roll = -st_sign * (t_roll + side_sign * tau_sw_x)
        stance_yaw = -st_sign * t_yaw
        return stance_pitch, stance_roll, stance_yaw

    def _holding(
        self, q: FloatArray, qd: FloatArray, hip_torque: tuple[FloatArray, FloatArray, FloatArray]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(B,) servo targets of the stance hip's flexion, abduction and twist under which it applies
        ``hip_torque``."""
        stance = self.stance_leg
        return (
            self._hold(q, qd, self._cols(stance, "hip_y"), hip_torque[0]),
            self._hold(q, qd, self._cols(stance, "hip_x"), hip_torque[1]),
            self._hold(q, qd, self._cols(stance, "hip_z"), hip_torque[2]),
        )

    def _stance_hip(
        self,
        u: FloatArray,
        att: Attitude,
        placement: _Placement,
        holding: tuple[FloatArray, FloatArray, FloatArray],
    ) -> None:
        """Write the stance hip's targets into ``u`` (B, U): as far as the stance foot is loaded, the
        ``holding`` targets (flexion, abduction, twist) that hold the pelvis; a stance foot not yet (or
        no longer) loaded holds nothing: its leg keeps reaching for the touchdown point. In flight the
        leaving leg swings forward instead."""
        g = self.gait
        runs = np.arange(u.shape[0])
        stance = self.stance_leg
        in_stance = self.phase == STANCE
        st_y = self._cols(stance, "hip_y")
        st_x = self._cols(stance, "hip_x")
        st_z = self._cols(stance, "hip_z")
        st_sign = self.sign[stance]
        w = self.load
        st_fwd, st_lateral = placement(st_sign)
        reach_y = st_fwd + att.pitch
        reach_x = st_sign * (st_lateral - att.roll)
        held_y = w * holding[0] + (1 - w) * reach_y
        held_x = w * holding[1] + (1 - w) * reach_x
        held_z = w * holding[2]
        u[runs, st_y] = np.where(in_stance, held_y, g.liftoff_hip + att.pitch)
        u[runs, st_x] = np.where(in_stance, held_x, st_sign * (st_sign * g.width - att.roll))
        u[runs, st_z] = np.where(in_stance, held_z, 0.0)
        st_knee_now = u[runs, self._cols(stance, "knee")]
        u[runs, self._cols(stance, "knee")] = np.where(
            in_stance, w * st_knee_now + (1 - w) * g.touchdown_knee, st_knee_now
        )

    def _arms_and_waist(self, u: FloatArray, q: FloatArray) -> None:
        """Write the arms' and the waist's targets into ``u`` (B, U), from the joint angles ``q`` (B, U):
        running, the arms swing against the legs and the waist leans a little."""
        g = self.gait
        running = self.running
        for s in (0, 1):
            u[:, self._col(s, "shoulder_y")] = (
                g.arm_swing * 0.5 * (q[:, self._col(1 - s, "hip_y")] - q[:, self._col(s, "hip_y")])
            )
            u[:, self._col(s, "elbow")] = np.where(running, g.elbow, self.stand[self._col(s, "elbow")])
        u[:, self.index["waist_y"]] = np.where(running, g.waist_lean, 0.0)

    def _stand(self, att: Attitude, rows: NDArray[np.bool_], sensordata: FloatArray) -> FloatArray:
        """Servo targets that keep standing runs up: the standing pose, held stiff, with the ankles
        leaning the body so that its centre of mass stays over the middle of the feet."""
        at = self.sensor_at
        com = sensordata[:, at["com"] : at["com"] + 3]
        feet = 0.5 * (
            sensordata[:, at["left_foot_pos"] : at["left_foot_pos"] + 3]
            + sensordata[:, at["right_foot_pos"] : at["right_foot_pos"] + 3]
        )
        heading = att.heading[rows]
        c, s = np.cos(heading), np.sin(heading)
        rel = com[:, :2] - feet[:, :2]
        fwd = c * rel[:, 0] + s * rel[:, 1] - 0.03  # balance over the middle of the feet
        vel = att.velocity[rows]
        u = np.repeat(self.stand[None], rows.sum(), axis=0)
        ix = self.index
        # ankle strategy: lean the stiff body back over the feet (positive ankle_y leans it forward)
        ankle = -(self.stand_gain[0] * fwd + self.stand_gain[1] * vel[:, 0])
        for side_name in body.SIDES:
            u[:, ix[f"{side_name}_ankle_y"]] = ankle
        return u


class KinematicSensors:
    """The controller's sensor readings computed from positions and velocities alone, for a closed loop
    whose state comes from an emulator rather than from MuJoCo's step.

    Every sensor but the feet's touch is kinematic (frame attitudes, centre of mass and its velocity,
    foot positions) and is computed exactly by MuJoCo's kinematics. A touch sensor reads a contact
    force, which only a dynamics step knows; here a foot's reading is estimated from how deep its
    geoms reach into the floor: nothing above ``DOWN_DEPTH``, else ``TOUCH_PER_M`` newtons per metre
    of depth with at least ``_DOWN_FORCE`` (a foot that touches is "down" for the state machine).
    On a run at 2 m/s the foot is down at the same physical steps as by the sensors 98.8 % of the time
    (deeper thresholds agree less). The controller reads a foot's load only up to 0.3 of the body's
    weight; a steep slope, so that a foot 0.2 mm in is fully loaded, is what keeps the gait running
    (at 20 kN/m, the least-squares slope, the figure falls within 2 s). Neither collision detection
    nor kinematics advances time: no physics step runs.

    Shapes: B runs; ``(B, nq)``, ``(B, nv)`` -> ``(B, nsensordata)``.
    """

    DOWN_DEPTH = 1e-4  # metres of the foot's geoms below the floor's surface
    TOUCH_PER_M = 1_000_000.0  # newtons per metre of depth: a foot 0.2 mm in bears the load the hip needs
    _DOWN_FORCE = 60.0  # what a foot that is just down reads: above the state machine's 50 N

    def __init__(self, m: mujoco.MjModel) -> None:
        self.m = m
        self.d = mujoco.MjData(m)
        sensor = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SENSOR, i): i for i in range(m.nsensor)}
        self.touch_at = {}
        for side in body.SIDES:
            for part, geom in (("sole", "foot"), ("toe_pad", "toes")):
                self.touch_at[int(m.geom(f"{side}_{geom}").id)] = int(m.sensor_adr[sensor[f"{side}_{part}"]])

    def read(self, qpos: FloatArray, qvel: FloatArray) -> FloatArray:
        m, d = self.m, self.d
        out = np.zeros((qpos.shape[0], m.nsensordata))
        for i in range(qpos.shape[0]):
            d.qpos[:] = qpos[i]
            d.qvel[:] = qvel[i]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_collision(m, d)
            mujoco.mj_sensorPos(m, d)
            mujoco.mj_comVel(m, d)
            mujoco.mj_subtreeVel(m, d)  # explicitly: mj_sensorVel skips it once computed for this MjData
            mujoco.mj_sensorVel(m, d)
            out[i] = d.sensordata
            depth = dict.fromkeys(self.touch_at, 0.0)
            for c in d.contact[: d.ncon]:
                for g in (int(c.geom1), int(c.geom2)):
                    if g in depth:
                        depth[g] += max(0.0, -float(c.dist))
            for g, at in self.touch_at.items():
                down = depth[g] > self.DOWN_DEPTH
                out[i, at] = max(self._DOWN_FORCE, self.TOUCH_PER_M * depth[g]) if down else 0.0
        return out


@dataclass
class RunResult:
    """A closed-loop run: states every ``every`` physical steps and whether and when each run fell."""

    states: FloatArray  # (B, T, nfull) MuJoCo full-physics states
    controls: FloatArray  # (B, T, U) servo targets applied from each recorded state on
    sensordata: FloatArray  # (B, T, nsensordata)
    dt: float  # seconds between records
    fell_at: FloatArray  # (B,) seconds into the run when the pelvis dropped, inf if it never did
    wall_s: float
    final_qpos: FloatArray  # (B, nq) where each run ended
    ends: FloatArray  # (B, T, nfull) the state each period ended in (before the next period's kick)

    @property
    def fell(self) -> NDArray[np.bool_]:
        return np.asarray(np.isfinite(self.fell_at))


def running_start(m: mujoco.MjModel, speed: float) -> FloatArray:
    """(nfull,) a full-physics state: standing on the left leg, knee bent, moving forward at ``speed``."""
    d = mujoco.MjData(m)
    ix = {name: k for k, name in enumerate(body.JOINTS)}
    ctl = RunnerController(m)
    pose = np.zeros(len(body.JOINTS))
    pose[ix["left_knee"]] = 0.3
    pose[ix["left_hip_y"]] = 0.15
    pose[ix["left_ankle_y"]] = 0.15
    pose[ix["right_knee"]] = 1.2
    pose[ix["right_hip_y"]] = 0.3
    d.qpos[ctl.qpos_at] = pose
    mujoco.mj_kinematics(m, d)
    foot = d.body("left_foot").xpos[2] - 0.07
    d.qpos[2] -= foot - 0.005
    d.qvel[0] = speed
    state = np.empty(mujoco.mj_stateSize(m, _STATE))
    mujoco.mj_getState(m, d, state, _STATE)
    return state


def perturbed_starts(
    m: mujoco.MjModel, speed: float, count: int, rng: np.random.Generator, noise: float = 0.01
) -> FloatArray:
    """(count, nfull) copies of ``running_start`` at ``speed`` with every velocity perturbed by
    N(0, ``noise``) (m/s, rad/s): the closed loop is chaotic, so how reliably a gait (or an emulator
    driven by it) stays up is measured over many such starts, not one."""
    start = np.repeat(running_start(m, speed)[None], count, axis=0)
    if noise > 0:
        start[:, 1 + m.nq : 1 + m.nq + m.nv] += rng.normal(0.0, noise, (count, m.nv))
    return start


_QPOS_AT = 1  # where qpos starts in a full-physics state: time, qpos, qvel, ...


def _batch_size(start: FloatArray, speeds: FloatArray, gait: Gait | None) -> int:
    """The batch: one run per start (B|1, nfull), per target speed (B|1,), or per value of a gait
    parameter given as an array."""
    sizes = [np.size(v) for v in vars(gait).values()] if gait is not None else []
    return max(start.shape[0], speeds.size, *sizes)


class _Noise:
    """The noise ``run`` adds: kicks to the state each control period starts from (hinge angles and
    velocities) and to the servo targets, at per-run levels, all drawn from one generator."""

    def __init__(
        self,
        batch: int,
        control_noise: float | FloatArray,
        state_noise: tuple[float | FloatArray, float | FloatArray],
        seed: int,
    ) -> None:
        self.rng = np.random.default_rng(seed)
        # per-run noise levels, (B, 1): a batch's runs may each draw their own
        self.kick_angle, self.kick_rate, self.target_noise = (
            np.broadcast_to(np.asarray(level, float), (batch,))[:, None]
            for level in (*state_noise, control_noise)
        )

    def kick(self, m: mujoco.MjModel, state: FloatArray) -> None:
        """Move the (B, nfull) full-physics states off the gait's own, in place: every hinge angle and
        every velocity."""
        if self.kick_angle.any() or self.kick_rate.any():
            batch = state.shape[0]
            hinges = slice(_QPOS_AT + 7, _QPOS_AT + m.nq)
            qvel_at = _QPOS_AT + m.nq
            state[:, hinges] += self.kick_angle * self.rng.standard_normal((batch, m.nq - 7))
            state[:, qvel_at : qvel_at + m.nv] += self.kick_rate * self.rng.standard_normal((batch, m.nv))

    def targets(self, targets: FloatArray, low: FloatArray, high: FloatArray) -> FloatArray:
        """(B, U) servo targets with noise added, kept within the control range ``low``..``high``."""
        if self.target_noise.any():
            return np.clip(targets + self.target_noise * self.rng.standard_normal(targets.shape), low, high)
        return targets


class _Physics:
    """MuJoCo's side of ``run``: each control period is one ``mujoco.rollout`` of ``control_every``
    physical steps of every run, with its servo targets (and a push on ``push_body``) held."""

    def __init__(
        self,
        m: mujoco.MjModel,
        batch: int,
        control_every: int,
        threads: int,
        ctrl_ids: NDArray[np.int_],
        push_body: str,
    ) -> None:
        self.m = m
        self.models = [m] * batch
        self.datas = [mujoco.MjData(m) for _ in range(max(1, min(threads, batch)))]
        self.nstep = control_every
        nstate = mujoco.mj_stateSize(m, _STATE)
        ncontrol = mujoco.mj_stateSize(m, _CONTROL)
        # where the controls lie in a control vector: read from one whose controls are marked
        self.probe = mujoco.MjData(m)
        self.probe.ctrl[:] = np.arange(m.nu) + 1000.0
        cvec = np.empty(ncontrol)
        mujoco.mj_getState(m, self.probe, cvec, _CONTROL)
        ctrl_at = int(np.flatnonzero(cvec == 1000.0)[0])
        self.ctrl_cols = ctrl_at + ctrl_ids
        self.xfrc_at = ctrl_at + m.nu
        body_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, push_body)
        self.push_at = self.xfrc_at + 6 * body_id  # the pushed body's force (x, y, z) in xfrc_applied
        self.control = np.zeros((batch, control_every, ncontrol))
        self.sensordata = np.zeros((batch, control_every, m.nsensordata))
        self.out_state = np.zeros((batch, control_every, nstate))

    def first_sensordata(self, state: FloatArray) -> FloatArray:
        """(B, nfull) -> (B, nsensordata): the first sensor reading, one forward pass per start (with
        the probe's marked controls still set, as the committed runs were made)."""
        m, probe = self.m, self.probe
        sens = np.zeros((state.shape[0], m.nsensordata))
        for i in range(state.shape[0]):
            mujoco.mj_setState(m, probe, state[i], _STATE)
            mujoco.mj_forward(m, probe)
            sens[i] = probe.sensordata
        return sens

    def step(
        self,
        state: FloatArray,
        targets: FloatArray,
        pushed: NDArray[np.bool_] | None,
        push_force: FloatArray | None,
    ) -> tuple[FloatArray, FloatArray]:
        """One control period from the (B, nfull) states with the (B, U) servo targets held, the runs
        ``pushed`` (B,) pushed by ``push_force`` (B, 3): the (B, nfull) states it ends in and the
        (B, nsensordata) sensors there."""
        control = self.control
        control[:, :, self.ctrl_cols] = targets[:, None, :]
        control[:, :, self.xfrc_at :] = 0.0
        if pushed is not None and push_force is not None:
            control[pushed, :, self.push_at : self.push_at + 3] = push_force[pushed, None, :]
        rollout.rollout(
            self.models,
            self.datas,
            state,
            control,
            control_spec=int(_CONTROL),
            skip_checks=True,
            nstep=self.nstep,
            state=self.out_state,
            sensordata=self.sensordata,
        )
        return self.out_state[:, -1].copy(), self.sensordata[:, -1].copy()


@dataclass
class _Records:
    """What ``run`` records of each control period: (B, T, ·) arrays, T = 0 when it records nothing."""

    states: FloatArray  # (B, T, nfull) the state each period starts from
    controls: FloatArray  # (B, T, U) the servo targets held over it
    sensordata: FloatArray  # (B, T, nsensordata) the sensors the controller read
    ends: FloatArray  # (B, T, nfull) the state it ends in

    @classmethod
    def empty(cls, m: mujoco.MjModel, batch: int, periods: int) -> _Records:
        states = np.zeros((batch, periods, mujoco.mj_stateSize(m, _STATE)))
        return cls(
            states,
            np.zeros((batch, periods, m.nu)),
            np.zeros((batch, periods, m.nsensordata)),
            np.zeros_like(states),
        )


class Controller(Protocol):
    """What ``run`` asks for servo targets: ``act`` (B, nq), (B, nv), (B, nsensordata), seconds →
    (B, U), kept within ``low``..``high`` (U,); ``ctrl_ids`` (U,) the actuators they go to."""

    low: FloatArray
    high: FloatArray
    ctrl_ids: NDArray[np.int_]

    def act(self, qpos: FloatArray, qvel: FloatArray, sensordata: FloatArray, dt: float) -> FloatArray: ...


def run(
    m: mujoco.MjModel,
    start: FloatArray,
    target_speed: FloatArray | float,
    seconds: float,
    *,
    gait: Gait | None = None,
    control_every: int = 3,
    push: Push | None = None,
    push_body: str = "torso",
    threads: int = 2,
    record: bool = True,
    kinematic: bool = False,
    control_noise: float | FloatArray = 0.0,
    state_noise: tuple[float | FloatArray, float | FloatArray] = (0.0, 0.0),
    seed: int = 0,
    controller: Controller | None = None,
) -> RunResult:
    """Run the closed loop from ``start`` (B|1, nfull) for ``seconds``.

    The controller sees the state every ``control_every`` physical steps and its targets are held in
    between; ``push`` adds a force on ``push_body`` (its force one vector, or one per run). A run has
    fallen once its pelvis is below 0.55 m. ``kinematic``: the controller reads ``KinematicSensors``
    (what it can read from an emulated state) instead of MuJoCo's sensors. ``control_noise``: Gaussian
    noise of this many radians is added to every servo target each control period (the neighbourhood
    of the gait, for training data), from ``seed``; ``state_noise`` (radians, and radians or metres
    per second) to every hinge angle and every velocity of the state the period starts from: states
    just off the gait, whose next states show how the body returns (an emulator's own rollouts leave
    the gait that way). ``controller``: another controller in this one's place (a learned policy).
    """
    start = np.atleast_2d(np.asarray(start, float))
    speeds = np.atleast_1d(np.asarray(target_speed, float))
    batch = _batch_size(start, speeds, gait)
    state = np.repeat(start, batch // start.shape[0], axis=0)
    ctl: Controller
    if controller is None:
        ctl = RunnerController(m, gait)
        ctl.reset(batch, speeds)
    else:
        ctl = controller
    physics = _Physics(m, batch, control_every, threads, ctl.ctrl_ids, push_body)
    dt = m.opt.timestep * control_every
    periods = round(seconds / dt)
    sens = physics.first_sensordata(state)
    records = _Records.empty(m, batch, periods if record else 0)
    fell_at = np.full(batch, np.inf)
    t0 = time.perf_counter()
    observer = KinematicSensors(m) if kinematic else None
    noise = _Noise(batch, control_noise, state_noise, seed)
    push_force = None if push is None else np.broadcast_to(np.asarray(push.force, float), (batch, 3))
    qpos_cols = slice(_QPOS_AT, _QPOS_AT + m.nq)
    qvel_cols = slice(_QPOS_AT + m.nq, _QPOS_AT + m.nq + m.nv)
    for k in range(periods):
        noise.kick(m, state)
        qpos = state[:, qpos_cols]
        qvel = state[:, qvel_cols]
        if observer is not None:
            sens = observer.read(qpos, qvel)
        targets = noise.targets(ctl.act(qpos, qvel, sens, dt), ctl.low, ctl.high)
        now = k * dt
        pushed = push.active(now, batch) if push is not None else None
        if record:
            records.states[:, k] = state
            records.controls[:, k] = targets
            records.sensordata[:, k] = sens
        state, sens = physics.step(state, targets, pushed, push_force)
        if record:
            records.ends[:, k] = state
        down = (state[:, _QPOS_AT + 2] < 0.55) & ~np.isfinite(fell_at)
        fell_at[down] = now + dt
    wall = time.perf_counter() - t0
    return RunResult(
        records.states,
        records.controls,
        records.sensordata,
        dt,
        fell_at,
        wall,
        state[:, qpos_cols].copy(),
        records.ends,
    )


Step = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
"""One emulated super-step: states (B, S), servo targets (B, U), push forces (B, 2) -> states (B, S)."""


@dataclass
class EmulatedRun:
    """A closed loop on an emulator: emulator states every super-step, and when each run fell."""

    states: FloatArray  # (B, T + 1, S) emulator states, the start first
    controls: FloatArray  # (B, T, U) servo targets held over each super-step
    dt: float  # seconds per super-step
    fell_at: FloatArray  # (B,) seconds, inf if never


def run_emulated(
    model: PhysicalModel,
    step: Step,
    substeps: int,
    start: FloatArray,
    target_speed: FloatArray | float,
    seconds: float,
    *,
    gait: Gait | None = None,
    push: Push | None = None,
) -> EmulatedRun:
    """The running controller on an emulator: like ``run`` with ``kinematic=True`` and
    ``control_every=substeps``, but every super-step is ``step`` (the emulator, whose controls are the
    servo targets and whose force inputs are the push on the torso, world x and y) instead of
    MuJoCo's physical steps. ``start`` (B|1, nfull) full-physics states, as ``run`` takes."""
    m = model.mj_model
    start = np.atleast_2d(np.asarray(start, float))
    speeds = np.atleast_1d(np.asarray(target_speed, float))
    batch = max(start.shape[0], speeds.size)
    state = model.from_physics(np.repeat(start, batch // start.shape[0], axis=0))
    ctl = RunnerController(m, gait)
    ctl.reset(batch, speeds)
    observer = KinematicSensors(m)
    dt = m.opt.timestep * substeps
    periods = round(seconds / dt)
    qpos_at = 1  # full physics: time, qpos, qvel, ...
    qpos_cols = np.arange(qpos_at, qpos_at + m.nq)
    qvel_cols = np.arange(qpos_at + m.nq, qpos_at + m.nq + m.nv)
    push_force = None if push is None else np.broadcast_to(np.asarray(push.force, float), (batch, 3))
    states = np.zeros((batch, periods + 1, model.state_size))
    controls = np.zeros((batch, periods, model.num_controls))
    states[:, 0] = state
    fell_at = np.full(batch, np.inf)
    for k in range(periods):
        full = model.to_physics(state)
        qpos, qvel = full[:, qpos_cols], full[:, qvel_cols]
        targets = ctl.act(qpos, qvel, observer.read(qpos, qvel), dt)
        now = k * dt
        forces = np.zeros((batch, model.num_forces))
        if push is not None and push_force is not None:
            pushed = push.active(now, batch)
            forces[pushed, :2] = push_force[pushed, :2]
        nxt = step(state, targets, forces)
        broken = ~np.isfinite(nxt).all(axis=1)
        if broken.any():  # a run that went non-finite has fallen; it stays where it was
            fell_at[broken & ~np.isfinite(fell_at)] = now
            nxt[broken] = state[broken]
        state = nxt
        states[:, k + 1] = state
        controls[:, k] = targets
        down = (full[:, qpos_cols[2]] < 0.55) & ~np.isfinite(fell_at)
        fell_at[down] = now
    return EmulatedRun(states, controls, dt, fell_at)


class RunnerDriver:
    """The running controller as a ``neuroanimator.sim.driver.Driver`` of one run: what the emulator
    service runs for a session of the runner's emulator, and for its MuJoCo shadow. It reads
    ``KinematicSensors`` (the emulated state has no contact forces), as ``run_emulated`` does."""

    def __init__(self, model: PhysicalModel, substeps: int, params: dict[str, float]) -> None:
        self.model = model
        m = model.mj_model
        self.dt = m.opt.timestep * substeps
        self.controller = RunnerController(m)
        self.observer = KinematicSensors(m)
        self.speed = float(params.get("speed", DRIVER_SPEED))
        self.controller.reset(1, self.speed)
        self.qpos_cols = np.arange(1, 1 + m.nq)  # full physics: time, qpos, qvel, ...
        self.qvel_cols = np.arange(1 + m.nq, 1 + m.nq + m.nv)

    def start(self) -> FloatArray:
        """(S,) a running stride's start at the target speed (``running_start``)."""
        return np.asarray(self.model.from_physics(running_start(self.model.mj_model, self.speed)[None])[0])

    def configure(self, params: dict[str, float]) -> None:
        self.speed = float(params.get("speed", self.speed))
        self.controller.target_speed[:] = self.speed
        self.controller.running = self.controller.target_speed > 0.0

    def act(self, state: NDArray[np.floating]) -> FloatArray:
        full = self.model.to_physics(np.asarray(state, float)[None])
        qpos, qvel = full[:, self.qpos_cols], full[:, self.qvel_cols]
        targets = self.controller.act(qpos, qvel, self.observer.read(qpos, qvel), self.dt)
        return np.asarray(targets[0])


DRIVER_SPEED = 2.0  # m/s: the driver's default target speed (between two the emulator was trained at)


def driver(model: PhysicalModel, substeps: int, params: dict[str, float]) -> RunnerDriver:
    """The ``ModelSpec.driver`` factory of the runner."""
    return RunnerDriver(model, substeps, params)
