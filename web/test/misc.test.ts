import { describe, expect, it } from 'vitest';
import { absolute, wsUrl } from '../src/config';
import { controlVariables, defaultTask, type TaskInfo } from '../src/api/controller';
import { describeFailure, unreachable } from '../src/api/http';
import { curvesOf, physicalRows, servedLabel } from '../src/api/measurements';
import type { VersionEval } from '../src/api/results.gen';
import { finiteRows } from '../src/pages/replay';
import { aligned, extent, isDecade, logRange, roundUp, tickLabel } from '../src/ui/series';

describe('config', () => {
  it('resolves service URLs against the page', () => {
    expect(absolute('/api/emulator', 'http://host:8080/index.html')).toBe('http://host:8080/api/emulator');
    expect(absolute('http://127.0.0.1:8000/', 'http://x/')).toBe('http://127.0.0.1:8000');
    expect(wsUrl('https://h/api/emulator', '/ws/sessions/a?mode=realtime', 'https://h/')).toBe('wss://h/api/emulator/ws/sessions/a?mode=realtime');
    expect(wsUrl('http://127.0.0.1:8000', '/ws/sessions/a', 'http://x/')).toBe('ws://127.0.0.1:8000/ws/sessions/a');
  });
});

describe('errors in plain words', () => {
  it("uses the service's message", () => {
    const e = describeFailure('emulator', 422, 'Unprocessable', { error: 'wrong_length', message: 'controls must have 4 values' });
    expect(e.message).toBe('The emulator service refused the request: controls must have 4 values');
    expect(e.code).toBe('wrong_length');
  });

  it('says when there is no message, and when the service is down', () => {
    expect(describeFailure('controller', 502, 'Bad Gateway', null).message).toBe('The controller service answered 502 Bad Gateway.');
    expect(unreachable('controller', 'http://127.0.0.1:8001').message).toMatch(/not reachable at http:\/\/127\.0\.0\.1:8001/);
  });
});

describe('measurements', () => {
  const curve = { t: [0, 1], error: [0.1, 0.2] };
  const row = (substeps: number, c = curve): VersionEval => ({
    model: 'm',
    version: `n${substeps}-x`,
    substeps,
    one_step_rel_error: 0.001,
    linear_baseline_rel_error: 0.1,
    baseline_ratio: 100,
    rollout_error_curve: c,
    rollout_error_at_20s: 0.1,
    rollout_error_final: 0.2,
    architecture: { hidden: [64, 64], activation: 'tanh', weights: 100 },
  });

  it('reads the curves of every measured n in increasing n, or nothing', () => {
    expect(curvesOf(null)).toEqual([]);
    expect(curvesOf({ by_substeps: [row(100), row(25), row(50, { t: [], error: [] })] }).map((c) => c.substeps)).toEqual([25, 100]);
    expect(curvesOf({ by_substeps: [row(50)] })).toEqual([{ substeps: 50, version: 'n50-x', curve }]);
  });

  it('labels versions the emulator does not serve, and lists physical errors per version and quantity', () => {
    expect(servedLabel(50, true)).toBe('N^50');
    expect(servedLabel(25, false)).toBe('N^25 (not loaded)');
    const at = [{ t_s: 1, mean: 0.1, p90: 0.2 }];
    const rows = physicalRows({
      by_substeps: [
        { ...row(50), physical_errors: { root_position_m: at, attitude_deg: null, joint_angle_rad: [] } },
        { ...row(25), physical_errors: { attitude_deg: at } },
      ],
    });
    expect(rows.map((r) => [r.substeps, r.quantity])).toEqual([
      [25, 'attitude_deg'],
      [50, 'root_position_m'],
    ]);
    expect(physicalRows({ by_substeps: [row(50)] })).toEqual([]);
    expect(physicalRows(null)).toEqual([]);
  });
});

describe('replay', () => {
  it('replaces non-finite rows by the last finite one', () => {
    expect(finiteRows([[1, 2], [null, 3], [4, 5]])).toEqual([[1, 2], [1, 2], [4, 5]]);
    expect(finiteRows([[null, 1]])).toEqual([]);
  });
});

describe('plot helpers', () => {
  it('merges series on their own x values into aligned columns', () => {
    const cols = aligned([
      { name: 'a', xs: [0, 1, 2], ys: [1, 2, 3], color: '#fff' },
      { name: 'b', xs: [1, 3], ys: [5, 6], color: '#000' },
    ]);
    expect(cols).toEqual([
      [0, 1, 2, 3],
      [1, 2, 3, null],
      [null, 5, null, 6],
    ]);
    expect(aligned([])).toEqual([[]]);
  });

  it('leaves out what an axis cannot draw: non-finite values, and non-positive ones on a log axis', () => {
    const s = [{ name: 'a', xs: [0, 1, 2, 3], ys: [0, -1, NaN, 0.5], color: '#fff' }];
    expect(aligned(s, true)).toEqual([[0, 1, 2, 3], [null, null, null, 0.5]]);
    expect(aligned(s, false)).toEqual([[0, 1, 2, 3], [0, -1, null, 0.5]]);
  });

  it('makes whole-decade log ranges, finite extents and readable tick labels', () => {
    expect(logRange([0.02, 0.5])).toEqual([0.01, 1]);
    expect(logRange([3, 3])).toEqual([1, 10]);
    expect(logRange([0, -1])).toBeNull();
    expect(extent([3, NaN, -1, Infinity])).toEqual([-1, 3]);
    expect(extent([0, -2, 5], true)).toEqual([5, 5]);
    expect(extent([])).toBeNull();
    expect(tickLabel(0.1 + 0.2)).toBe('0.3');
    expect(tickLabel(1e-5)).toBe('1e-5');
    expect(tickLabel(250000)).toBe('3e5');
    expect(tickLabel(0)).toBe('0');
    expect(tickLabel(null)).toBe('');
    expect([0.0023, 0.2, 3, 7, 0, null].map(roundUp)).toEqual([0.005, 0.2, 5, 10, 1e-3, 1e-3]);
    expect([1e-4, 0.01, 1, 100, 0.02, 3, 0, -10, null].map(isDecade)).toEqual([true, true, true, true, false, false, false, false, false]);
  });
});

describe('defaults from what the services list', () => {
  // as GET /tasks lists the built-in tasks (only the fields the choice reads)
  const tasks: TaskInfo[] = [
    { name: 'pendulum-swing', model: 'pendulum-active', horizon: 40, points_per_step: 0.5, initial_controls: [0, 0, 0] },
    { name: 'lander-landing', model: 'lander', horizon: 40, points_per_step: 0.5, initial_controls: [16.2, 0, 0, 0] },
    { name: 'truck-parking', model: 'truck', horizon: 40, points_per_step: 0.5, initial_controls: [0, 0] },
  ];

  it('counts the control variables of a task (thesis 6.2: 60, 80 and 40)', () => {
    expect(tasks.map(controlVariables)).toEqual([60, 80, 40]);
    expect(controlVariables({ name: 'bare' })).toBe(Infinity);
  });

  it('opens the task asked for, else the smallest problem, else the first listed', () => {
    expect(defaultTask(tasks, 'lander-landing')?.name).toBe('lander-landing');
    expect(defaultTask(tasks, null)?.name).toBe('truck-parking');
    expect(defaultTask(tasks, 'no-such-task')?.name).toBe('truck-parking');
    expect(defaultTask([{ name: 'a' }, { name: 'b' }], null)?.name).toBe('a');
    expect(defaultTask([], null)).toBeUndefined();
  });
});
