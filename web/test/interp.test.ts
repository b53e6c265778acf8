import { describe, expect, it } from 'vitest';
import { lerpPose, locate, slerp, SnapshotBuffer, lerpPoses } from '../src/scene/interp';

describe('slerp', () => {
  it('ends at its inputs and stays unit length', () => {
    const a = [1, 0, 0, 0];
    const b = [Math.cos(0.5), 0, 0, Math.sin(0.5)]; // 1 rad about z
    expect(slerp(a, b, 0)).toEqual(a.map((v) => expect.closeTo(v, 9)));
    expect(slerp(a, b, 1).map((v) => +v.toFixed(9))).toEqual(b.map((v) => +v.toFixed(9)));
    const mid = slerp(a, b, 0.5);
    expect(Math.hypot(...mid)).toBeCloseTo(1, 12);
    expect(mid[3]).toBeCloseTo(Math.sin(0.25), 12); // half the angle
  });

  it('takes the shorter way round (q and -q are one rotation)', () => {
    const a = [1, 0, 0, 0];
    const b = [-Math.cos(0.1), 0, 0, -Math.sin(0.1)];
    const mid = slerp(a, b, 0.5);
    expect(Math.abs(mid[0]!)).toBeGreaterThan(0.99);
  });
});

describe('lerpPose', () => {
  it('interpolates positions linearly', () => {
    const p = lerpPose([0, 0, 0, 1, 0, 0, 0], [2, 4, -2, 1, 0, 0, 0], 0.25);
    expect(p.slice(0, 3)).toEqual([0.5, 1, -0.5]);
  });
});

describe('SnapshotBuffer', () => {
  it('samples between snapshots and holds at the ends', () => {
    const buf = new SnapshotBuffer<number[][]>(lerpPoses);
    expect(buf.sample(0)).toBeNull();
    buf.push(1000, [[0, 0, 0, 1, 0, 0, 0]]);
    buf.push(1500, [[1, 0, 0, 1, 0, 0, 0]]);
    expect(buf.sample(500)![0]![0]).toBe(0);
    expect(buf.sample(1250)![0]![0]).toBeCloseTo(0.5);
    expect(buf.sample(9999)![0]![0]).toBe(1);
  });

  it('keeps at most its capacity', () => {
    const buf = new SnapshotBuffer<number>((a, b, t) => a + (b - a) * t, 3);
    for (let i = 0; i < 10; i++) buf.push(i, i);
    expect(buf.size).toBe(3);
    expect(buf.sample(0)).toBe(7);
  });
});

describe('locate', () => {
  it('finds the segment and the fraction', () => {
    const times = [0, 0.5, 1, 1.5];
    expect(locate(times, 0.75)).toEqual({ i: 1, f: 0.5 });
    expect(locate(times, -1)).toEqual({ i: 0, f: 0 });
    expect(locate(times, 9)).toEqual({ i: 2, f: 1 });
  });
});
