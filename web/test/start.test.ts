import { describe, expect, it } from 'vitest';
import type { LayoutGroup } from '../src/api/emulator.gen';
import { restState, startFromQuery } from '../src/session/start';

const g = (name: string, kind: LayoutGroup['kind'], size: number, offset: number, source: LayoutGroup['source'] = 'qpos'): LayoutGroup => ({
  name,
  kind,
  size,
  offset,
  source,
  address: 0,
});

describe('rest state', () => {
  it('puts a free root where its MJCF does, at rest', () => {
    const lander = [g('position', 'position', 3, 0), g('orientation', 'quaternion', 4, 3), g('velocity', 'world_vector', 3, 7, 'qvel'), g('w', 'local_vector', 3, 10, 'qvel')];
    expect(restState(lander, [0, 0, 20, 1, 0, 0, 0])).toEqual([0, 0, 20, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
  });

  it('puts joints at 0 (a planar root on slides, hinges) and ball joints at the identity', () => {
    const truck = [g('position', 'position', 2, 0), g('heading', 'heading', 1, 2), g('velocity', 'world_vector', 2, 3, 'qvel'), g('yaw_rate', 'scalar', 1, 5, 'qvel')];
    expect(restState(truck, [0, 0, 0.5, 1, 0, 0, 0])).toEqual([0, 0, 0, 0, 0, 0]);
    const ball = [g('shoulder', 'local_quaternion', 4, 0), g('elbow', 'angle', 1, 4)];
    expect(restState(ball, undefined)).toEqual([1, 0, 0, 0, 0]);
    expect(restState([], undefined)).toBeNull();
  });

  it('reads the start asked for in the address', () => {
    expect(startFromQuery('model=lander&start=rest')).toEqual({ from: 'rest', seed: null });
    expect(startFromQuery('seed=7')).toEqual({ from: 'random', seed: 7 });
    expect(startFromQuery('seed=x&start=sideways')).toEqual({ from: null, seed: null });
  });
});
