import { describe, expect, it } from 'vitest';
import { ResolutionGovernor } from '../src/scene/quality';
import { angleBetween, gapLabel, poseGap, rootMoves } from '../src/scene/divergence';
import { envelopeText } from '../src/session/realtime';
import { outcomeSummary, verdictOf, verdictText } from '../src/pages/outcome';
import type { LayoutGroup } from '../src/api/emulator.gen';

/** Frames at `fps` for `seconds`, from `t0` (ms); returns the time after the last one. */
function run(g: ResolutionGovernor, fps: number, seconds: number, t0: number): number {
  let t = t0;
  for (let i = 0; i < fps * seconds; i++) {
    t += 1000 / fps;
    g.frame(t);
  }
  return t;
}

describe('resolution governor', () => {
  it('keeps full resolution at 60 fps', () => {
    const g = new ResolutionGovernor();
    run(g, 60, 5, 0);
    expect(g.scale).toBe(1);
    expect(g.fps).toBeCloseTo(60, 0);
  });

  it('steps down while slow, to its floor, and back up once fast again', () => {
    const g = new ResolutionGovernor({ min: 0.5 });
    let t = run(g, 20, 2.5, 0);
    expect(g.scale).toBeLessThan(1);
    t = run(g, 20, 20, t);
    expect(g.scale).toBe(0.5);
    t = run(g, 60, 4, t);
    expect(g.scale).toBe(0.5); // not at once: after a few good windows
    run(g, 60, 40, t);
    expect(g.scale).toBe(1);
  });

  it('steps down while frames are dropped, even at 50 fps, and settles where the display rate holds', () => {
    const g = new ResolutionGovernor();
    run(g, 50, 3, 0);
    expect(g.scale).toBeLessThan(1);
    expect(g.fps).toBeCloseTo(50, 0);
  });

  it('keeps full resolution through a missed vsync now and then (one a second)', () => {
    const g = new ResolutionGovernor();
    run(g, 59, 30, 0);
    expect(g.scale).toBe(1);
  });

  it('steps down when a few frames a second are late (58 fps is not 60)', () => {
    const g = new ResolutionGovernor();
    run(g, 58, 3, 0);
    expect(g.scale).toBe(0.8);
  });

  it('tries a scale that proved too slow again less and less often (no flicker)', () => {
    // a view that keeps 60 fps at 0.8 of the resolution and drops frames (55 fps) at full resolution
    const g = new ResolutionGovernor({ maxUpAfter: 1000 });
    let t = 0;
    let changes = 0;
    let at60 = 0;
    const seconds = 600;
    while (t < seconds * 1000) {
      const fps = g.scale > 0.8 ? 55 : 60; // each frame's time follows the scale it is drawn at
      if (fps === 60) at60 += 1000 / fps;
      t += 1000 / fps;
      if (g.frame(t)) changes += 1;
    }
    expect(g.scale).toBeLessThanOrEqual(0.8);
    expect(g.scale).toBeGreaterThanOrEqual(0.64); // it found the scale that holds, not the floor
    expect(at60 / t).toBeGreaterThan(0.95);
    expect(changes).toBeLessThan(16); // each retry waits twice as long: about log2 of the time
    expect(g.waitFor(1)).toBeGreaterThan(24);
  });
});

const lander: LayoutGroup[] = [
  { name: 'position', kind: 'position', size: 3, source: 'qpos', address: 0, offset: 0 },
  { name: 'orientation', kind: 'quaternion', size: 4, source: 'qpos', address: 3, offset: 3 },
];
const pendulum: LayoutGroup[] = [{ name: 'angles', kind: 'angle', size: 3, source: 'qpos', address: 0, offset: 0 }];

describe('divergence', () => {
  it('measures the root gap of a free model, the largest body gap of a fixed one', () => {
    expect(rootMoves(lander)).toBe(true);
    expect(rootMoves(pendulum)).toBe(false);
    expect(gapLabel(lander)).toBe('root position error');
    const a = [[0, 0, 0, 1, 0, 0, 0], [0, 0, -1, 1, 0, 0, 0]];
    const b = [[0, 0, 0, 1, 0, 0, 0], [3, 0, -5, 1, 0, 0, 0]];
    expect(poseGap(a, b, true)!.position).toBe(0);
    expect(poseGap(a, b, false)!.position).toBe(5);
    expect(poseGap([], b, true)).toBeNull();
  });

  it('measures attitude in degrees, q and -q alike', () => {
    const s = Math.SQRT1_2;
    expect(angleBetween([1, 0, 0, 0], [s, 0, 0, s])).toBeCloseTo(90);
    expect(angleBetween([1, 0, 0, 0], [-1, 0, 0, 0])).toBeCloseTo(0);
  });
});

describe('the trained envelope', () => {
  it('says nothing while inside, or when the service does not send the flag', () => {
    expect(envelopeText({ type: 'state' })).toBeNull();
    expect(envelopeText({ outside_envelope: false })).toBeNull();
    expect(envelopeText({ outside_envelope: [] })).toBeNull();
  });

  it('names what is outside when told', () => {
    expect(envelopeText({ outside_envelope: true })).toMatch(/outside the range of states/);
    expect(envelopeText({ outside_envelope: ['position', 'velocity'] })).toBe('outside the trained range of position, velocity');
    expect(envelopeText({ outside_envelope: { position: true, velocity: false } })).toBe('outside the trained range of position');
  });
});

describe('outcome', () => {
  it("states the result's own verdicts, never its own judgement", () => {
    expect(verdictText(true)).toBe('meets the criterion');
    expect(verdictText(false)).toBe('misses the criterion');
    expect(outcomeSummary({ success_criterion: 'c', success_emulator: true, success_physics: false })).toMatch(/meets .* on the emulator but misses it on MuJoCo/);
    expect(outcomeSummary({ success_criterion: 'c', success_emulator: true, success_physics: true })).toMatch(/on MuJoCo and on the emulator/);
    expect(outcomeSummary({ success_criterion: 'c', success_emulator: false, success_physics: false })).toMatch(/misses/);
    expect(outcomeSummary({ success_criterion: null, success_emulator: null, success_physics: null })).toMatch(/no success criterion/);
  });
  it('calls a job without a criterion done, not succeeded, and still gives its error', () => {
    // the run ended normally (status "succeeded") with the pendulum 2.83 rad from its goal
    const r = { success_criterion: null, success_emulator: null, success_physics: null, final_error_physics: 2.83, final_error_emulator: 0.4 };
    expect(verdictOf(r)).toBe('done, no criterion');
    const line = outcomeSummary(r);
    expect(line).toMatch(/^Done, no criterion/);
    expect(line).toMatch(/2\.83 on MuJoCo/);
    expect(line).not.toMatch(/succeed/);
    expect(verdictOf({ ...r, verdict: 'done, no criterion' })).toBe('done, no criterion');
    // as the service words an empty criterion (dolphin-swim): still no criterion, not "misses" it
    expect(outcomeSummary({ ...r, success_criterion: 'no success criterion' })).toMatch(/^Done, no criterion/);
    expect(verdictOf({ success_criterion: 'c', success_emulator: true, success_physics: false })).toBe('done, criterion met on the emulator only');
    expect(verdictOf({ success_criterion: 'c', success_emulator: false, success_physics: true })).toBe('succeeded');
  });
});
