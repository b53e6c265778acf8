// Where a Playground session starts: the model's rest state (its pose in the MJCF, MuJoCo's qpos0,
// at rest), or a random typical state the emulator service draws (reproducible with a seed).
import type { LayoutGroup } from '../api/emulator.gen';

/**
 * The rest state from the layout and the root body's rest pose [x, y, z, qw, qx, qy, qz]: a free
 * root (3 positions and a quaternion) where the MJCF puts it; joints (hinges, slides, a planar root's
 * heading) at 0; ball joints at the identity; every velocity 0. null for a layout without groups.
 * Only for a service whose geometry has no `rest_state`: a joint with a `ref` rests off 0 (the
 * dolphin's nodes), which the layout cannot tell.
 */
export function restState(layout: LayoutGroup[], rootPose: number[] | undefined): number[] | null {
  if (!layout.length) return null;
  const size = Math.max(...layout.map((g) => g.offset + g.size));
  const state = new Array<number>(size).fill(0);
  const pose = rootPose ?? [0, 0, 0, 1, 0, 0, 0];
  for (const g of layout) {
    if (g.kind === 'position' && g.size === 3) pose.slice(0, 3).forEach((v, i) => (state[g.offset + i] = v));
    else if (g.kind === 'quaternion') pose.slice(3, 7).forEach((v, i) => (state[g.offset + i] = v));
    else if (g.kind === 'local_quaternion') state[g.offset] = 1;
  }
  return state;
}

export type StartFrom = 'rest' | 'random' | 'driver';

/** The start asked for in the page's address: `start=rest|random|driver` (driver: driven by the model's
 * own controller, for a model that has one), `seed=N` (a random start). */
export function startFromQuery(query: string): { from: StartFrom | null; seed: number | null } {
  const q = new URLSearchParams(query);
  const raw = q.get('seed');
  const seed = raw !== null && /^\d+$/.test(raw) ? Number(raw) : null;
  const start = q.get('start');
  const from: StartFrom | null = start === 'rest' || start === 'random' || start === 'driver' ? start : seed !== null ? 'random' : null;
  return { from, seed };
}

/** The Playground's address for a model, asking it to start a session at rest as soon as it opens. */
export function driveHash(model: string): string {
  return `#/playground?${new URLSearchParams({ model, start: 'rest', drive: '1' }).toString()}`;
}

/** Whether the page's address asks the Playground to start a session at once (`drive=1`). */
export function driveNow(query: string): boolean {
  return new URLSearchParams(query).get('drive') === '1';
}
