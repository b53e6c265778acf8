// Editing a goal state through the state layout's group kinds (the manifest's one truth about what
// each number means): the root's `position` group gives world x and y (dragging on the ground), a
// `heading` angle or the root `quaternion` gives the heading about z, and every group read from qpos
// (positions, angles) is editable by number. Velocities are left as the task set them.
import type { LayoutGroup } from '../api/emulator.gen';

export interface TargetHandles {
  xy: [number, number] | null; // state indices of the root's world x and y
  heading: { kind: 'angle'; index: number } | { kind: 'quat'; offset: number } | null;
  editable: number[]; // state indices a person may type
}

/** Whether a job's objective weighs its final state against a target (state weights not all zero). A
 * task without one (dolphin-swim: as far as it can) has no goal to draw, drag or type. */
export function hasGoalState(weights: unknown): boolean {
  return !Array.isArray(weights) || weights.some((w) => typeof w === 'number' && w !== 0);
}

/** No handles: a goal that cannot be moved. */
export const NO_HANDLES: TargetHandles = { xy: null, heading: null, editable: [] };

export function targetHandles(layout: LayoutGroup[]): TargetHandles {
  const pos = layout.find((g) => g.kind === 'position' && g.size >= 2);
  const heading = layout.find((g) => g.kind === 'heading' && g.size === 1);
  const quat = layout.find((g) => g.kind === 'quaternion' && g.size === 4);
  const editable = layout
    .filter((g) => g.source === 'qpos' && g.kind !== 'quaternion' && g.kind !== 'local_quaternion')
    .flatMap((g) => Array.from({ length: g.size }, (_, i) => g.offset + i));
  return {
    xy: pos ? [pos.offset, pos.offset + 1] : null,
    heading: heading ? { kind: 'angle', index: heading.offset } : quat ? { kind: 'quat', offset: quat.offset } : null,
    editable,
  };
}

export function withXY(state: number[], h: TargetHandles, x: number, y: number): number[] {
  const out = [...state];
  if (h.xy) {
    out[h.xy[0]] = x;
    out[h.xy[1]] = y;
  }
  return out;
}

/** The heading (radians about z) of a state. */
export function headingOf(state: number[], h: TargetHandles): number {
  if (!h.heading) return 0;
  if (h.heading.kind === 'angle') return state[h.heading.index] ?? 0;
  const o = h.heading.offset;
  const [w, x, y, z] = [state[o] ?? 1, state[o + 1] ?? 0, state[o + 2] ?? 0, state[o + 3] ?? 0];
  return Math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z));
}

/** The state turned to `angle` about z (a quaternion root keeps its tilt). */
export function withHeading(state: number[], h: TargetHandles, angle: number): number[] {
  const out = [...state];
  if (!h.heading) return out;
  if (h.heading.kind === 'angle') {
    out[h.heading.index] = angle;
    return out;
  }
  const o = h.heading.offset;
  const d = angle - headingOf(state, h);
  const [cw, cz] = [Math.cos(d / 2), Math.sin(d / 2)];
  const [w, x, y, z] = [state[o] ?? 1, state[o + 1] ?? 0, state[o + 2] ?? 0, state[o + 3] ?? 0];
  // (cw, 0, 0, cz) ⊗ (w, x, y, z): a turn about the world z axis
  out[o] = cw * w - cz * z;
  out[o + 1] = cw * x - cz * y;
  out[o + 2] = cw * y + cz * x;
  out[o + 3] = cw * z + cz * w;
  return out;
}
