import { describe, expect, it } from 'vitest';
import type { LayoutGroup } from '../src/api/emulator.gen';
import { hasGoalState, headingOf, targetHandles, withHeading, withXY } from '../src/session/target';

const truck: LayoutGroup[] = [
  { name: 'position', kind: 'position', size: 2, offset: 0, source: 'qpos', address: 0 },
  { name: 'heading', kind: 'heading', size: 1, offset: 2, source: 'qpos', address: 2 },
  { name: 'velocity', kind: 'world_vector', size: 2, offset: 3, source: 'qvel', address: 0 },
  { name: 'yaw_rate', kind: 'scalar', size: 1, offset: 5, source: 'qvel', address: 2 },
];
const lander: LayoutGroup[] = [
  { name: 'position', kind: 'position', size: 3, offset: 0, source: 'qpos', address: 0 },
  { name: 'orientation', kind: 'quaternion', size: 4, offset: 3, source: 'qpos', address: 3 },
  { name: 'velocity', kind: 'world_vector', size: 3, offset: 7, source: 'qvel', address: 0 },
  { name: 'angular_velocity', kind: 'local_vector', size: 3, offset: 10, source: 'qvel', address: 3 },
];
const pendulum: LayoutGroup[] = [
  { name: 'angles', kind: 'angle', size: 3, offset: 0, source: 'qpos', address: 0 },
  { name: 'rates', kind: 'scalar', size: 3, offset: 3, source: 'qvel', address: 0 },
];

describe('targetHandles', () => {
  it('reads the layout kinds', () => {
    expect(targetHandles(truck)).toEqual({ xy: [0, 1], heading: { kind: 'angle', index: 2 }, editable: [0, 1, 2] });
    expect(targetHandles(lander)).toEqual({ xy: [0, 1], heading: { kind: 'quat', offset: 3 }, editable: [0, 1, 2] });
    expect(targetHandles(pendulum)).toEqual({ xy: null, heading: null, editable: [0, 1, 2] });
  });
});

describe('editing a goal', () => {
  it('moves x and y', () => {
    const h = targetHandles(truck);
    expect(withXY([0, 0, 1, 0, 0, 0], h, 3, -4)).toEqual([3, -4, 1, 0, 0, 0]);
  });

  it('turns a heading angle and a quaternion root alike', () => {
    const t = targetHandles(truck);
    expect(headingOf(withHeading([0, 0, 0, 0, 0, 0], t, 0.7), t)).toBeCloseTo(0.7);
    const l = targetHandles(lander);
    const s = [0, 0, 5, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0];
    const turned = withHeading(s, l, 1.2);
    expect(headingOf(turned, l)).toBeCloseTo(1.2);
    expect(Math.hypot(...turned.slice(3, 7))).toBeCloseTo(1);
    expect(headingOf(withHeading(turned, l, -0.4), l)).toBeCloseTo(-0.4);
  });
});

describe('hasGoalState', () => {
  it('is a goal when any state weight is set, or when the job does not say', () => {
    expect(hasGoalState([0, 0, 1])).toBe(true);
    expect(hasGoalState(undefined)).toBe(true);
    expect(hasGoalState([0, 0, 0])).toBe(false); // dolphin-swim: as far as it can, no goal state
    expect(hasGoalState([])).toBe(false);
  });
});
