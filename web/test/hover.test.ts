import { describe, expect, it } from 'vitest';
import type { LayoutGroup } from '../src/api/emulator.gen';
import { holdControls, verticalVelocityIndex } from '../src/session/hover';

const g = (name: string, kind: LayoutGroup['kind'], size: number, offset: number, source: LayoutGroup['source']): LayoutGroup => ({ name, kind, size, offset, source, address: 0 });
const LANDER = [g('position', 'position', 3, 0, 'qpos'), g('orientation', 'quaternion', 4, 3, 'qpos'), g('velocity', 'world_vector', 3, 7, 'qvel'), g('w', 'local_vector', 3, 10, 'qvel')];
const REST = [0, 0, 20, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0];
const JETS = [
  { low: 0, high: 32.4 },
  { low: -1, high: 1 },
  { low: -1, high: 1 },
  { low: -1, high: 1 },
];

/** The lander's physics over one super-step of `dt` from rest: mass 100, lunar gravity, 10 N per unit of
 * main jet, a slightly nonlinear engine (as an emulator may learn it). */
function lander(dt: number, calls: number[][][]) {
  return async (controls: number[][]) => {
    calls.push(controls);
    return controls.map((u) => {
      const thrust = 10 * u[0]! * (1 + 0.002 * u[0]!);
      const s = [...REST];
      s[9] = (thrust / 100 - 1.62) * dt;
      return s;
    });
  };
}

describe('hover', () => {
  it('finds the vertical velocity of a free root only', () => {
    expect(verticalVelocityIndex(LANDER)).toBe(9);
    const truck = [g('position', 'position', 2, 0, 'qpos'), g('heading', 'heading', 1, 2, 'qpos'), g('velocity', 'world_vector', 2, 3, 'qvel')];
    expect(verticalVelocityIndex(truck)).toBe(-1);
    expect(verticalVelocityIndex([g('angles', 'angle', 3, 0, 'qpos')])).toBe(-1);
  });

  it('starts the lander at the thrust that holds it still', async () => {
    const calls: number[][][] = [];
    const hold = await holdControls(LANDER, JETS, [0, 0, 0, 0], 0.5, lander(0.5, calls));
    expect(hold).not.toBeNull();
    // 16.2 with a linear engine; the secant step corrects for the nonlinearity the first guess misses
    const exact = (-1 + Math.sqrt(1 + 4 * 0.002 * 16.2)) / (2 * 0.002);
    expect(hold![0]).toBeCloseTo(exact, 1);
    expect(hold!.slice(1)).toEqual([0, 0, 0]); // the attitude jets do not lift: they stay at rest
    expect(calls).toHaveLength(2); // one step per control and at rest, then one check
    expect(calls[0]).toHaveLength(5);
  });

  it('leaves a model that does not fall (on the ground, in water) at rest', async () => {
    const still = async (controls: number[][]) => controls.map(() => [...REST]);
    expect(await holdControls(LANDER, JETS, [0, 0, 0, 0], 0.5, still)).toBeNull();
    expect(await holdControls([g('angles', 'angle', 3, 0, 'qpos')], JETS, [0, 0, 0, 0], 0.5, still)).toBeNull();
  });

  it('gives up when even full thrust cannot hold it', async () => {
    const weak = async (controls: number[][]) => controls.map((u) => Object.assign([...REST], { 9: (u[0]! / 100 - 1.62) * 0.5 }));
    expect(await holdControls(LANDER, JETS, [0, 0, 0, 0], 0.5, weak)).toBeNull();
  });
});
