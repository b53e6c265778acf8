import { describe, expect, it } from 'vitest';
import type { PolicyJobResult, PolicyJobStatus, PolicyManifest } from '../src/api/controller';
import type { EnvelopeGroup, LayoutGroup } from '../src/api/emulator.gen';
import { policiesQuery } from '../src/pages/policies';
import { goalHandles, goalOutside, goalPoint, goalState, kicked, movedGoal, roundGoal, sameGoal, seededRandom, sliderRange, timeToCheck } from '../src/policies/goal';
import { controlsLine, fromPolicyStatus, isPolicyEnded, metricsRows, onPolicyEvent, percent, policyStatusLine, progressRows, seconds, startPolicyView, withResult, type PolicyTrainingView } from '../src/policies/progress';

const group = (name: string, kind: LayoutGroup['kind'], offset: number, size: number, source: LayoutGroup['source']): LayoutGroup => ({ name, kind, offset, size, source, address: offset });

// the state layouts of the committed emulators the built-in policy tasks drive
const LANDER = {
  layout: [group('position', 'position', 0, 3, 'qpos'), group('orientation', 'quaternion', 3, 4, 'qpos'), group('velocity', 'world_vector', 7, 3, 'qvel'), group('angular_velocity', 'local_vector', 10, 3, 'qvel')],
  labels: ['position.x', 'position.y', 'position.z', 'orientation.w', 'orientation.x', 'orientation.y', 'orientation.z', 'velocity.x', 'velocity.y', 'velocity.z', 'angular_velocity.x', 'angular_velocity.y', 'angular_velocity.z'],
  target: [0, 0, 0, 1, 0, 0, 0, 0, 0, -0.3, 0, 0, 0],
};
const TRUCK = {
  layout: [group('position', 'position', 0, 2, 'qpos'), group('heading', 'heading', 2, 1, 'qpos'), group('velocity', 'world_vector', 3, 2, 'qvel'), group('yaw_rate', 'scalar', 5, 1, 'qvel')],
  labels: ['position.x', 'position.y', 'heading', 'velocity.x', 'velocity.y', 'yaw_rate'],
};
const QUADROTOR = {
  layout: [group('root.pos', 'position', 0, 3, 'qpos'), group('root.quat', 'quaternion', 3, 4, 'qpos'), group('root.vel', 'world_vector', 7, 3, 'qvel'), group('root.angvel', 'local_vector', 10, 3, 'qvel')],
  labels: ['root.pos.x', 'root.pos.y', 'root.pos.z', 'root.quat.w', 'root.quat.x', 'root.quat.y', 'root.quat.z', 'root.vel.x', 'root.vel.y', 'root.vel.z', 'root.angvel.x', 'root.angvel.y', 'root.angvel.z'],
  target: [0, 0, 10, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0],
};
const PENDULUM = {
  layout: [group('angles', 'angle', 0, 3, 'qpos'), group('rates', 'scalar', 3, 3, 'qvel')],
  labels: ['angles.j0', 'angles.j1', 'angles.j2', 'rates.j0', 'rates.j1', 'rates.j2'],
};

describe('a goal in the scene', () => {
  it("puts the lander's pad on the ground where the goal's x and y say, and a drag moves it there", () => {
    const h = goalHandles(['position.x', 'position.y'], LANDER.labels, LANDER.layout);
    expect([h.kind, h.x, h.y, h.z, h.heading, h.state]).toEqual(['ground', 0, 1, null, null, [0, 1]]);
    const state = goalState(LANDER.target, h, [3, -4]);
    expect(state.slice(0, 4)).toEqual([3, -4, 0, 1]); // upright, on the ground at the pad
    expect(state.slice(7)).toEqual(LANDER.target.slice(7)); // the rest of the target state as the task has it
    expect(goalPoint(state, h)).toEqual([3, -4, 0]);
    const dragged = movedGoal([3, -4], h, 5.5, 2, 7); // a ground goal has no z to take
    expect(dragged).toEqual([5.5, 2]);
    expect(goalPoint(goalState(LANDER.target, h, dragged), h)).toEqual([5.5, 2, 0]);
  });

  it("places the truck's spot on the ground with its heading a goal variable of its own", () => {
    const h = goalHandles(['position.x', 'position.y', 'heading'], TRUCK.labels, TRUCK.layout);
    expect([h.kind, h.x, h.y, h.z, h.heading]).toEqual(['ground', 0, 1, null, 2]);
    const state = goalState([0, 0, 0, 0, 0, 0], h, [-8, 6, 1.2]);
    expect(state).toEqual([-8, 6, 1.2, 0, 0, 0]);
    expect(goalPoint(state, h)).toEqual([-8, 6, 0]); // a planar root: on the ground
    expect(movedGoal([-8, 6, 1.2], h, 1, 2)).toEqual([1, 2, 1.2]); // a drag keeps the heading
    expect(sliderRange(-Math.PI, Math.PI, true)).toEqual([-Math.PI, Math.PI]);
  });

  it("moves the quadrotor's target in space: a drag on its level, the height apart", () => {
    const h = goalHandles(['root.pos.x', 'root.pos.y', 'root.pos.z'], QUADROTOR.labels, QUADROTOR.layout);
    expect([h.kind, h.x, h.y, h.z]).toEqual(['space', 0, 1, 2]);
    const goal = [1, -2, 11];
    expect(goalPoint(goalState(QUADROTOR.target, h, goal), h)).toEqual([1, -2, 11]);
    expect(movedGoal(goal, h, 2.5, 0)).toEqual([2.5, 0, 11]); // dragged on the plane at its height
    expect(movedGoal(goal, h, 2.5, 0, 8)).toEqual([2.5, 0, 8]);
  });

  it("sets the pendulum's goal angles with no place to drag", () => {
    const h = goalHandles(['angles.j0', 'angles.j1', 'angles.j2'], PENDULUM.labels, PENDULUM.layout);
    expect([h.kind, h.x, h.y]).toEqual(['pose', null, null]);
    expect(goalState([0, 0, 0, 0, 0, 0], h, [0.5, -0.2, 1])).toEqual([0.5, -0.2, 1, 0, 0, 0]);
    expect(goalPoint([0.5, -0.2, 1, 0, 0, 0], h)).toBeNull();
  });

  it('leaves out a goal variable the state does not have', () => {
    const h = goalHandles(['position.x', 'speed'], LANDER.labels, LANDER.layout);
    expect(h.state).toEqual([0, -1]);
    expect(h.kind).toBe('pose'); // no y: nothing to drag on a plane
    expect(goalState([1, 2, 3], h, [9, 9])).toEqual([9, 2, 3]);
  });

  it("takes a goal that is no state variable as a command (the runner's speed): nothing to draw", () => {
    const h = goalHandles(['speed'], LANDER.labels, LANDER.layout);
    expect([h.kind, h.x, h.y, h.z, h.heading, h.state]).toEqual(['command', null, null, null, null, [-1]]);
    expect(goalState([1, 2, 3], h, [2.0])).toEqual([1, 2, 3]);
    expect(goalPoint([1, 2, 3], h)).toBeNull();
  });

  it('takes a policy with no goal at all (standing up) as a command with nothing to set', () => {
    const h = goalHandles([], LANDER.labels, LANDER.layout);
    expect([h.kind, h.state]).toEqual(['command', []]);
    expect(goalState([1, 2, 3], h, [])).toEqual([1, 2, 3]);
  });

  it('names the goal variables outside the trained range, a bound itself inside', () => {
    const names = ['position.x', 'position.y'];
    expect(goalOutside([15, -15], [-15, -15], [15, 15], names)).toEqual([]);
    expect(goalOutside([15.000001, -15], [-15, -15], [15, 15], names)).toEqual([]); // float32 rounding
    expect(goalOutside([16, -3], [-15, -15], [15, 15], names)).toEqual(['position.x']);
    expect(goalOutside([0, -20], [-15, -15], [15, 15], names)).toEqual(['position.y']);
    const [lo, hi] = sliderRange(-15, 15);
    expect(lo < -15 && hi > 15).toBe(true); // a slider reaches past the range, to show the flag
  });

  it('rounds a goal to what is worth sending and compares it with the float32 echo', () => {
    expect(roundGoal([3.14159265358, -0.000012345678, NaN])).toEqual([3.14159, -0.0000123457, 0]);
    expect(sameGoal([3.14159, 2], [3.1415901, 2.0000001])).toBe(true);
    expect(sameGoal([3.1, 2], [3.2, 2])).toBe(false);
    expect(sameGoal([1], null)).toBe(false);
  });

  it('counts down a timed goal to its check, and stops at zero', () => {
    expect(timeToCheck(10, 0, 80, 0.25)).toBe(17.5);
    expect(timeToCheck(100, 30, 80, 0.25)).toBe(2.5);
    expect(timeToCheck(200, 30, 80, 0.25)).toBe(0);
  });
});

describe('a kick', () => {
  const envelope: EnvelopeGroup[] = [
    { group: 'position', low: [-30, -30, -1], high: [30, 30, 40] },
    { group: 'velocity', low: [-10, -10, -12], high: [10, 10, 6] },
    { group: 'angular_velocity', low: [-2, -2, -2], high: [2, 2, 2] },
  ];
  const state = [1, 2, 20, 1, 0, 0, 0, 0.5, -0.5, -1, 0, 0, 0];

  it('moves every velocity, and nothing else, by a felt amount within the envelope', () => {
    const out = kicked(state, LANDER.layout, envelope, seededRandom(7));
    expect(out.slice(0, 7)).toEqual(state.slice(0, 7)); // positions and attitude as they were
    const moved = out.slice(7).map((v, i) => Math.abs(v - state[7 + i]!));
    expect(moved.every((d) => d > 0)).toBe(true);
    // at least half the strength of the half-range (unless the envelope's edge stopped it)
    expect(moved[0]! >= 0.5 * 0.35 * 10 - 1e-9 || Math.abs(out[7]!) === 10).toBe(true);
    out.slice(7, 10).forEach((v, i) => expect(v >= envelope[1]!.low[i]! && v <= envelope[1]!.high[i]!).toBe(true));
    out.slice(10).forEach((v) => expect(Math.abs(v) <= 2).toBe(true));
  });

  it('is repeatable with a seed, and different with another', () => {
    expect(kicked(state, LANDER.layout, envelope, seededRandom(3))).toEqual(kicked(state, LANDER.layout, envelope, seededRandom(3)));
    expect(kicked(state, LANDER.layout, envelope, seededRandom(3))).not.toEqual(kicked(state, LANDER.layout, envelope, seededRandom(4)));
  });

  it('stays inside the envelope however hard, and kicks a velocity without a range by up to its strength', () => {
    const hard = kicked(state, LANDER.layout, envelope, seededRandom(1), 50);
    hard.slice(7, 10).forEach((v, i) => expect([envelope[1]!.low[i], envelope[1]!.high[i]]).toContain(v));
    const bare = kicked([0, 0, 0, 0, 0, 0], PENDULUM.layout, null, seededRandom(2), 0.5);
    expect(bare.slice(0, 3)).toEqual([0, 0, 0]);
    bare.slice(3).forEach((v) => expect(Math.abs(v) >= 0.25 && Math.abs(v) <= 0.5).toBe(true));
  });
});

/** Events as the controller service sends them for one policy job. */
function run(events: [string, Record<string, unknown>][]): PolicyTrainingView {
  return events.reduce((v, [e, d]) => onPolicyEvent(v, e, d), startPolicyView('j1', 'lander-landing'));
}

const POLICY: PolicyManifest = {
  name: 'lander-landing',
  version: 'p-20261201T120000',
  created: '2026-12-01T12:00:00Z',
  model: 'lander',
  emulator_version: 'n25-20261123T162353',
  substeps: 25,
  super_timestep: 0.25,
  state_size: 13,
  state_labels: LANDER.labels,
  control_names: ['main_jet', 'roll', 'pitch', 'yaw'],
  goal_variables: ['position.x', 'position.y'],
  goal_low: [-15, -15],
  goal_high: [15, 15],
  goal_default: [0, 0],
  goal_period_steps: 80,
  check_steps: 80,
  metrics: { success_physics: 0.42, success_emulator: 0.5, evaluate_runs: 100, mujoco_steps: 123456, iterations: 61, wall_s: 8.4, stop: 'budget' },
};

describe('a policy job, from its events', () => {
  it('follows the iterations, the loss curve and each MuJoCo check to the end', () => {
    const v = run([
      ['status', { status: 'queued', attempt: 1 }],
      ['status', { status: 'running', attempt: 1 }],
      ['progress', { iteration: 1, loss: 5.2, success_physics: null, mujoco_steps: 2000, elapsed_s: 0.4, attempt: 1 }],
      ['progress', { iteration: 2, loss: 4.1, success_physics: 0.1, mujoco_steps: 4000, elapsed_s: 0.8, attempt: 1 }],
      ['progress', { iteration: 3, loss: 3.9, success_physics: 0.1, mujoco_steps: 4000, elapsed_s: 1.1, attempt: 1 }],
      ['progress', { iteration: 4, loss: null, success_physics: 0.3, mujoco_steps: 6000, elapsed_s: 1.5, attempt: 1 }],
      ['progress', { iteration: 5, loss: 3.5, success_physics: 0.3, mujoco_steps: 6000, elapsed_s: 1.6, attempt: 1 }],
      ['progress', { iteration: 6, loss: 3.4, success_physics: 0.3, mujoco_steps: 8000, elapsed_s: 2.5, attempt: 1 }],
    ]);
    expect([v.status, v.iteration, v.loss, v.successPhysics, v.mujocoSteps, v.elapsedS]).toEqual(['running', 6, 3.4, 0.3, 8000, 2.5]);
    expect(v.losses).toEqual([
      [1, 5.2],
      [2, 4.1],
      [3, 3.9],
      [4, null], // a loss that was not finite: a gap in the curve
      [5, 3.5],
      [6, 3.4],
    ]);
    // a check is where the last check's share changes (the events repeat it every iteration), or where
    // MuJoCo ran again (a check that found the same share)
    expect(v.successes).toEqual([
      [2, 0.1],
      [4, 0.3],
      [6, 0.3],
    ]);
    const mid = run([['progress', { iteration: 4, loss: null, success_physics: 0.3, mujoco_steps: 6000, elapsed_s: 1.5, attempt: 1 }]]);
    expect(policyStatusLine(mid)).toBe('Training lander-landing: iteration 4, loss –, success on MuJoCo 30 %, 1.5 s in.');
    expect(progressRows(v).map((r) => r[1])).toEqual(['6', '3.4', '30 %', '8,000', '2.5 s']);
    const done = onPolicyEvent(v, 'end', { status: 'succeeded', reason: null, iterations: 7 });
    expect([done.status, done.iteration, done.error, isPolicyEnded(done)]).toEqual(['succeeded', 7, null, true]);
    expect(onPolicyEvent(done, 'progress', { iteration: 9, loss: 1 })).toBe(done); // an ended job stays ended
  });

  it('says why a job failed or was cancelled, and starts afresh on a new attempt', () => {
    const requeued = run([
      ['progress', { iteration: 3, loss: 2, success_physics: 0.2, mujoco_steps: 10, attempt: 1 }],
      ['status', { status: 'queued', attempt: 2, reason: 'its worker stopped answering' }],
    ]);
    expect([requeued.status, requeued.attempt, requeued.iteration, requeued.losses, requeued.successes]).toEqual(['queued', 2, 0, [], []]);
    expect(policyStatusLine(requeued)).toBe('Job j1 (lander-landing) is waiting for a controller worker (queued again: its worker stopped answering).');
    const failed = onPolicyEvent(requeued, 'end', { status: 'failed', reason: 'no goal MuJoCo reaches' });
    expect(policyStatusLine(failed)).toBe('Job j1 failed: no goal MuJoCo reaches');
    expect(onPolicyEvent(startPolicyView('j2', 't'), 'end', { status: 'weird' }).status).toBe('failed');
    const cancelled = onPolicyEvent(startPolicyView('j3', 't'), 'end', { status: 'cancelled' });
    expect([cancelled.status, cancelled.error]).toEqual(['cancelled', 'the job cancelled']);
    expect(onPolicyEvent(startPolicyView('j4', 't'), 'progress', { loss: 1 }).iteration).toBe(0); // no iteration: ignored
  });

  it('takes a polled status over the events, keeping the longer curve', () => {
    const v = run([
      ['progress', { iteration: 1, loss: 3, success_physics: null, attempt: 1 }],
      ['progress', { iteration: 2, loss: 2, success_physics: null, attempt: 1 }],
      ['progress', { iteration: 3, loss: 1.5, success_physics: null, attempt: 1 }],
    ]);
    const status: PolicyJobStatus = {
      id: 'j1',
      status: 'running',
      task: 'lander-landing',
      model: 'lander',
      emulator_version: 'n25',
      seconds: 8,
      refine: false,
      created_at: 0,
      attempt: 1,
      iteration: 4,
      loss: 1.2,
      success_physics: 0.25,
      mujoco_steps: 900,
      elapsed_s: 2,
      loss_history: [
        { iteration: 2, value: 2 },
        { iteration: 4, value: 1.2 },
      ],
    };
    const p = fromPolicyStatus(v, status);
    expect([p.iteration, p.loss, p.successPhysics, p.mujocoSteps]).toEqual([4, 1.2, 0.25, 900]);
    expect(p.losses.map((x) => x[0])).toEqual([1, 2, 3]); // the thinned history is shorter: the events' curve stays
    expect(p.successes).toEqual([[4, 0.25]]);
    expect(fromPolicyStatus(p, status).successes).toEqual([[4, 0.25]]); // the same check polled again
    const failed = fromPolicyStatus(p, { ...status, status: 'failed', error: 'past its time limit' });
    expect([failed.status, failed.error]).toEqual(['failed', 'past its time limit']);
  });

  it("ends with the result's histories and the stored policy's metrics", () => {
    const v = run([['progress', { iteration: 1, loss: 3, success_physics: 0.5, attempt: 1 }]]);
    const result: PolicyJobResult = {
      id: 'j1',
      status: 'succeeded',
      policy: POLICY,
      iterations: 61,
      loss_history: [
        { iteration: 1, value: 3 },
        { iteration: 61, value: 0.4 },
      ],
      success_history: [
        { iteration: 20, value: 0.3 },
        { iteration: 40, value: null },
        { iteration: 60, value: 0.45 },
      ],
    };
    const done = withResult(onPolicyEvent(v, 'end', { status: 'succeeded', iterations: 61 }), result);
    expect(done.successes).toEqual([
      [20, 0.3],
      [60, 0.45],
    ]);
    expect([done.iteration, done.successPhysics, done.mujocoSteps, done.result?.policy?.version]).toEqual([61, 0.45, 123456, 'p-20261201T120000']);
    expect(policyStatusLine(done)).toBe('lander-landing is trained: policy version p-20261201T120000.');
    const rows = Object.fromEntries(metricsRows(POLICY));
    expect(rows['success on MuJoCo']).toBe('42 % of 100 held-out runs');
    expect(rows['success on the emulator']).toBe('50 % of 100 held-out runs');
    expect(rows['MuJoCo steps used']).toBe('123,456');
    expect(rows.goals).toBe('position.x -15…15, position.y -15…15');
    expect(rows['emulator refinements']).toBeUndefined(); // a service that does not count them
    const refined = { ...POLICY, metrics: { ...POLICY.metrics, refinements: 3 } as PolicyManifest['metrics'] };
    expect(Object.fromEntries(metricsRows(refined))['emulator refinements']).toBe('3');
    const stopped = withResult(startPolicyView('j5', 'lander-landing', 'running'), { id: 'j5', status: 'cancelled', policy: null });
    expect(policyStatusLine(stopped)).toBe('Job j5 was cancelled; no policy was stored.');
  });

  it("follows a suite task's return on MuJoCo at each check, and states its policy by its return", () => {
    let v = startPolicyView('j7', 'cartpole-swingup');
    v = onPolicyEvent(v, 'progress', { iteration: 1, loss: -0.2, success_physics: null, return_physics: null, mujoco_steps: 0, attempt: 1 });
    v = onPolicyEvent(v, 'progress', { iteration: 2, loss: -0.3, return_physics: 212.5, mujoco_steps: 40000, attempt: 1 });
    v = onPolicyEvent(v, 'progress', { iteration: 3, loss: -0.3, return_physics: 212.5, mujoco_steps: 40000, attempt: 1 });
    v = onPolicyEvent(v, 'progress', { iteration: 4, loss: -0.4, return_physics: 640, mujoco_steps: 80000, attempt: 1 });
    expect(v.returns).toEqual([
      [2, 212.5],
      [4, 640],
    ]);
    expect([v.returnPhysics, v.successPhysics, v.successes]).toEqual([640, null, []]);
    expect(Object.fromEntries(progressRows(v).map(([k, val]) => [k, val]))['return on MuJoCo (last check)']).toBe('640');
    const status: PolicyJobStatus = { id: 'j7', status: 'running', task: 'cartpole-swingup', model: 'cartpole', emulator_version: 'n5', seconds: 60, refine: true, created_at: 0, attempt: 1, iteration: 6, return_physics: 701, mujoco_steps: 120000 };
    const polled = fromPolicyStatus(v, status);
    expect(polled.returns.at(-1)).toEqual([6, 701]);
    const policy: PolicyManifest = {
      ...POLICY,
      name: 'cartpole-swingup',
      goal_variables: [],
      goal_low: [],
      goal_high: [],
      goal_default: [],
      metrics: { ...POLICY.metrics, success_physics: null, success_emulator: null, return_physics: 873.4, return_emulator: 850.1, evaluate_runs: 10 } as PolicyManifest['metrics'],
    };
    const done = withResult(v, { id: 'j7', status: 'succeeded', policy, iterations: 9, return_history: [{ iteration: 5, value: 700 }, { iteration: 9, value: 873.4 }] });
    expect([done.returns, done.returnPhysics]).toEqual([[[5, 700], [9, 873.4]], 873.4]);
    const rows = Object.fromEntries(metricsRows(policy));
    expect([rows['return on MuJoCo'], rows['return on the emulator'], rows['success on MuJoCo']]).toEqual(['873 (mean of 10 episodes)', '850 (mean of 10 episodes)', undefined]);
    expect(rows.goals).toBe('none (the task has no parameters)');
    expect(rows['falls on MuJoCo']).toBeUndefined(); // none measured, none said
    const walker: PolicyManifest = {
      ...policy,
      metrics: { ...policy.metrics, outside_envelope: 0.0412, root_drift_m: 0.3456, seed_returns: [474.2, 911.4], falls: [{ episode: 3, time_s: 2.5, state: [0.1] }, { episode: 7, time_s: 0.4, state: [0.2] }] } as PolicyManifest['metrics'],
    };
    const trust = Object.fromEntries(metricsRows(walker));
    expect(trust["emulated states outside the emulator's envelope"]).toBe('4 %');
    expect(trust["the emulator's root off MuJoCo's at 1 s"]).toBe('0.35 m');
    expect(trust['falls on MuJoCo']).toBe('2 of 10 episodes (the first at 0.4 s, episode 7)');
    // falls it got up from are said apart: some, or all
    const fell = (again: (number | null)[]) => ({
      ...walker,
      metrics: { ...walker.metrics, falls: again.map((a, i) => ({ episode: i, time_s: 1.5 + i, state: [0.1], up_again_s: a })) } as PolicyManifest['metrics'],
    });
    expect(Object.fromEntries(metricsRows(fell([3.5, null])))['falls on MuJoCo']).toBe('2 of 10 episodes (the first at 1.5 s, episode 0; up again in 1)');
    expect(Object.fromEntries(metricsRows(fell([3.5, 6.0])))['falls on MuJoCo']).toBe('2 of 10 episodes (the first at 1.5 s, episode 0; up again in all)');
    expect(trust['seeds trained side by side']).toBe('2, returns 474, 911 (the best kept)');
    expect(rows['seeds trained side by side']).toBeUndefined(); // one seed: nothing to say
  });

  it('writes shares and durations for people', () => {
    expect([percent(0.426), percent(null), percent(1)]).toEqual(['43 %', '–', '100 %']);
    expect([seconds(8.44), seconds(125), seconds(null)]).toEqual(['8.4 s', '2 min 5 s', '–']);
  });
});

describe("the page's address", () => {
  it('names the policy to drive, whether to start it, and the task to train', () => {
    expect(policiesQuery('policy=lander%2Flander-landing&drive=1&seed=3')).toEqual({ policy: 'lander/lander-landing', drive: true, task: null });
    expect(policiesQuery('task=truck-parking')).toEqual({ policy: null, drive: false, task: 'truck-parking' });
  });
});

describe('controlsLine', () => {
  it('names every control when there are few', () => {
    expect(controlsLine(['main', 'yaw'], [0.5, -0.25])).toBe('main 0.5, yaw -0.25');
  });
  it('names a control without a name by its index', () => {
    expect(controlsLine(['main'], [0.5, 1])).toBe('main 0.5, u1 1');
  });
  it('gives the count and the largest in magnitude past the limit (the runner: 29 controls on one line)', () => {
    const names = Array.from({ length: 29 }, (_, i) => `j${i}`);
    const values = names.map((_, i) => (i === 7 ? -0.9 : i === 20 ? 0.8 : 0.01 * i));
    const line = controlsLine(names, values, 2);
    expect(line).toBe('29, the largest j7 -0.9, j20 0.8');
  });
  it('shows exactly `shown` controls by name at the limit', () => {
    expect(controlsLine(['a', 'b', 'c', 'd'], [1, 2, 3, 4])).not.toContain('the largest');
    expect(controlsLine(['a', 'b', 'c', 'd', 'e'], [1, 2, 3, 4, 5])).toMatch(/^5, the largest e /);
  });
});
