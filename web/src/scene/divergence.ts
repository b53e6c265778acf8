// How far the emulator is from MuJoCo: the distance between their roots' positions (metres) and the
// angle between their roots' orientations (degrees), from body poses [x, y, z, qw, qx, qy, qz]. For a
// model whose root is fixed to the world (a pendulum), the root does not move, so the position gap is
// the largest over its bodies (the tip's, in practice).
import type { LayoutGroup } from '../api/emulator.gen';
import type { Pose } from './interp';

export interface Gap {
  position: number; // metres
  attitude: number; // degrees
}

/** Whether the model's root moves in the world (its state has a root position). */
export function rootMoves(layout: LayoutGroup[]): boolean {
  return layout.some((g) => g.kind === 'position');
}

/** The label of the position gap for a model: the root's, or the largest over its bodies. */
export function gapLabel(layout: LayoutGroup[]): string {
  return rootMoves(layout) ? 'root position error' : 'largest body position error';
}

/** The angle (degrees) between two unit quaternions [w, x, y, z]; q and -q are the same rotation. */
export function angleBetween(a: number[], b: number[]): number {
  const dot = Math.abs(a.reduce((s, v, i) => s + v * (b[i] ?? 0), 0));
  return (2 * Math.acos(Math.min(1, dot)) * 180) / Math.PI;
}

export function poseGap(a: Pose[], b: Pose[], root: boolean): Gap | null {
  const ra = a[0];
  const rb = b[0];
  if (!ra || !rb) return null;
  const dist = (p: Pose, q: Pose): number => Math.hypot((p[0] ?? 0) - (q[0] ?? 0), (p[1] ?? 0) - (q[1] ?? 0), (p[2] ?? 0) - (q[2] ?? 0));
  const position = root ? dist(ra, rb) : Math.max(...a.map((p, i) => dist(p, b[i] ?? p)));
  return { position, attitude: angleBetween(ra.slice(3, 7), rb.slice(3, 7)) };
}
