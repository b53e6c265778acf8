import { describe, expect, it } from 'vitest';
import { headingOf, targetHandles, withHeading, withXY } from '../src/session/target';

const truck = [
  { name: 'position', kind: 'position', size: 2, offset: 0, source: 'qpos' },
  { name: 'heading', kind: 'heading', size: 1, offset: 2, source: 'qpos' },
  { name: 'velocity', kind: 'world_vector', size: 2, offset: 3, source: 'qvel' },
  { name: 'yaw_rate', kind: 'scalar', size: 1, offset: 5, source: 'qvel' },
];
const lander = [
  { name: 'position', kind: 'position', size: 3, offset: 0, source: 'qpos' },
  { name: 'orientation', kind: 'quaternion', size: 4, offset: 3, source: 'qpos' },
  { name: 'velocity', kind: 'world_vector', size: 3, offset: 7, source: 'qvel' },
  { name: 'angular_velocity', kind: 'local_vector', size: 3, offset: 10, source: 'qvel' },
];
const pendulum = [
  { name: 'angles', kind: 'angle', size: 3, offset: 0, source: 'qpos' },
  { name: 'rates', kind: 'scalar', size: 3, offset: 3, source: 'qvel' },
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
