// A policy's goal and the scene: which goal variables are the root's world position (dragged in the
// view: on the ground for the lander's pad and the truck's spot, on a horizontal plane with a height
// slider for the quadrotor's target) or its heading, the state the goal marker is drawn at (the task's
// target state with the goal in place), and what the page checks of a goal itself (outside the trained
// range). Also the "kick" of a session whose model has no force inputs: its state with the velocities
// perturbed, which a new session of the same policy starts from. A goal none of whose variables is a
// state variable (the runner's speed) is a command: set with sliders, no marker drawn for it. Pure
// functions: no DOM, no three.js.
import type { EnvelopeGroup, LayoutGroup } from '../api/emulator.gen';

export type GoalKind = 'ground' | 'space' | 'pose' | 'command';

export interface GoalHandles {
  /** The state index of each goal variable (-1: the state has no such label). */
  state: number[];
  /** Goal indices of the root's world x, y and z (null: not a goal variable). */
  x: number | null;
  y: number | null;
  z: number | null;
  /** The goal index of a heading angle about z (the truck's). */
  heading: number | null;
  /** The state offset of the root's position group and its size (2: a planar root, 3: a free one). */
  root: { offset: number; size: number } | null;
  /** ground: x and y on the ground plane; space: x, y and z; pose: none of them (joint angles);
   * command: no goal variable is a state variable (a speed to run at): there is no place or pose to
   * draw. */
  kind: GoalKind;
}

export function goalHandles(goalVariables: string[], stateLabels: string[], layout: LayoutGroup[]): GoalHandles {
  const state = goalVariables.map((v) => stateLabels.indexOf(v));
  const pos = layout.find((g) => g.kind === 'position' && g.size >= 2) ?? null;
  const heading = layout.find((g) => g.kind === 'heading' && g.size === 1) ?? null;
  const at = (index: number | undefined): number | null => {
    if (index === undefined) return null;
    const i = state.indexOf(index);
    return i >= 0 ? i : null;
  };
  const x = pos ? at(pos.offset) : null;
  const y = pos ? at(pos.offset + 1) : null;
  const z = pos && pos.size >= 3 ? at(pos.offset + 2) : null;
  const kind: GoalKind = x !== null && y !== null ? (z !== null ? 'space' : 'ground') : state.every((i) => i < 0) ? 'command' : 'pose';
  return { state, x, y, z, heading: heading ? at(heading.offset) : null, root: pos ? { offset: pos.offset, size: pos.size } : null, kind };
}

/** `base` (S) with the goal's values at their state indices: the state the goal marker is drawn at. */
export function goalState(base: number[], h: GoalHandles, goal: number[]): number[] {
  const out = [...base];
  h.state.forEach((s, i) => {
    const v = goal[i];
    if (s >= 0 && s < out.length && v !== undefined) out[s] = v;
  });
  return out;
}

/** Where the goal marker is in MuJoCo's frame, [x, y, z]: the root's position in the goal state (a
 * planar root on the ground, z 0); null for a goal that is no place (joint angles). */
export function goalPoint(state: number[], h: GoalHandles): [number, number, number] | null {
  if (h.kind === 'pose' || h.kind === 'command' || !h.root) return null;
  const o = h.root.offset;
  return [state[o] ?? 0, state[o + 1] ?? 0, h.root.size >= 3 ? (state[o + 2] ?? 0) : 0];
}

/** The goal moved to (x, y) on its plane, and to height z when given (a goal in space). */
export function movedGoal(goal: number[], h: GoalHandles, x: number, y: number, z?: number): number[] {
  const out = [...goal];
  if (h.x !== null) out[h.x] = x;
  if (h.y !== null) out[h.y] = y;
  if (z !== undefined && h.z !== null) out[h.z] = z;
  return out;
}

/** The goal variables outside `low`..`high` (what the service reports as `goal_outside`, for a goal
 * the page has not sent yet); float32 rounding at a bound is inside. */
export function goalOutside(goal: number[], low: number[], high: number[], names: string[]): string[] {
  const tol = (v: number) => 1e-6 * Math.max(1, Math.abs(v));
  return names.filter((_, i) => {
    const v = goal[i];
    const lo = low[i];
    const hi = high[i];
    if (v === undefined) return false;
    return (lo !== undefined && v < lo - tol(lo)) || (hi !== undefined && v > hi + tol(hi));
  });
}

/** A slider's range for a goal variable: its trained range and a quarter of it beyond either end, so
 * that a person can set a goal outside it (flagged) as well as inside; a heading stays within ±π. */
export function sliderRange(low: number, high: number, isHeading = false): [number, number] {
  if (isHeading) return [-Math.PI, Math.PI];
  const w = Math.max(high - low, 1e-6);
  return [low - w / 4, high + w / 4];
}

/** The goal, its values as sent: finite numbers rounded to float32 precision's worth (6 significant
 * digits), so that a goal dragged to the same place is the same goal. */
export function roundGoal(goal: number[]): number[] {
  return goal.map((v) => (Number.isFinite(v) ? Number(v.toPrecision(6)) : 0));
}

/** Whether two goals are the same (the service echoes float32 values). */
export function sameGoal(a: readonly number[] | null | undefined, b: readonly number[] | null | undefined): boolean {
  if (!a || !b || a.length !== b.length) return false;
  return a.every((v, i) => Math.abs(v - (b[i] ?? NaN)) <= 1e-5 * Math.max(1, Math.abs(v)));
}

/**
 * The state after a kick: every velocity (the layout's groups read from qvel) moved by up to
 * `strength` of its half-range in the emulator's envelope, in a random direction (`random()` in
 * [0, 1)), and kept within the envelope (a kick must not leave what the emulator was trained on).
 * Positions and orientations are left as they are. Without an envelope group a velocity's half-range
 * is taken as 1.
 */
export function kicked(state: number[], layout: LayoutGroup[], envelope: EnvelopeGroup[] | null | undefined, random: () => number, strength = 0.35): number[] {
  const out = [...state];
  for (const g of layout) {
    if (g.source !== 'qvel') continue;
    const env = envelope?.find((e) => e.group === g.name);
    for (let i = 0; i < g.size; i++) {
      const s = g.offset + i;
      const lo = env?.low[i] ?? null;
      const hi = env?.high[i] ?? null;
      const half = lo !== null && hi !== null && hi > lo ? (hi - lo) / 2 : 1;
      // at least half the strength, either way: a kick is felt
      const push = strength * half * (0.5 + 0.5 * random()) * (random() < 0.5 ? -1 : 1);
      let v = (out[s] ?? 0) + push;
      if (lo !== null && v < lo) v = lo;
      if (hi !== null && v > hi) v = hi;
      out[s] = v;
    }
  }
  return out;
}

/** A timed policy's time left until its goal's check, in seconds: the check comes `checkSteps`
 * super-steps after the goal was set (0 once past it). */
export function timeToCheck(steps: number, goalStep: number, checkSteps: number, superTimestep: number): number {
  return Math.max(0, checkSteps - (steps - goalStep)) * superTimestep;
}

/** A small seeded random number generator (mulberry32), for kicks that a test can repeat. */
export function seededRandom(seed: number): () => number {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}
