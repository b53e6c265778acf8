// Where a Playground session's controls start: for a model that falls at rest (a free body in the air,
// such as the lander or the quadrotor), the controls that hold it still, so that it hovers where it
// starts instead of dropping through its pad with the jets off.
//
// The services say nothing of gravity or mass, so the hold is not computed from them: it is measured
// from the emulator itself. From the rest state it takes one super-step with the controls at rest and
// one per control at its high end, reads how each changes the vertical velocity, raises the controls
// that lift together by the share of their range that cancels the fall, and checks that with one more
// step (a secant correction for a response that is not quite linear). For the lander this finds the
// main jet at its hover thrust (mass 100 under lunar gravity, 10 N per unit: 16.2, the middle of its
// trained range 0 … 32.4), within the emulator's error.
import type { ControlInfo, LayoutGroup } from '../api/emulator.gen';

/** One super-step from the rest state under each of these control vectors: the next states. */
export type Probe = (controls: number[][]) => Promise<number[][]>;

/** The index of the root's vertical velocity in the state: a free root (a 3-D position) with a world
 * velocity; -1 for any other model (on rails, planar, fixed: gravity cannot pull it away). */
export function verticalVelocityIndex(layout: LayoutGroup[]): number {
  const position = layout.find((g) => g.kind === 'position' && g.size === 3 && g.source === 'qpos');
  const velocity = layout.find((g) => g.kind === 'world_vector' && g.size === 3 && g.source === 'qvel');
  return position && velocity ? velocity.offset + 2 : -1;
}

/**
 * The controls that hold a model still where it rests (`base` elsewhere), or null when it does not
 * fall with `base` (it stands on the ground, floats, or cannot fly), when nothing lifts it, or when
 * even every lifting control at its high end cannot hold it. `superDt` is the super-step in seconds: a
 * model falls when it gains more than 0.2 m/s² downwards.
 */
export async function holdControls(layout: LayoutGroup[], controls: Pick<ControlInfo, 'low' | 'high'>[], base: number[], superDt: number, probe: Probe): Promise<number[] | null> {
  const vz = verticalVelocityIndex(layout);
  if (vz < 0 || !controls.length) return null;
  const raisable = controls.map((_, i) => i).filter((i) => controls[i]!.high > (base[i] ?? 0));
  if (!raisable.length) return null;
  const at = (i: number, v: number): number[] => base.map((b, j) => (j === i ? v : b));
  const next = await probe([base, ...raisable.map((i) => at(i, controls[i]!.high))]);
  const v0 = next[0]?.[vz];
  if (v0 === undefined || !Number.isFinite(v0) || v0 > -0.2 * superDt) return null;
  // what each control at its high end adds to the vertical velocity; those that lift, lift together
  const gains = raisable.map((_, k) => (next[k + 1]?.[vz] ?? NaN) - v0);
  const most = Math.max(...gains.filter(Number.isFinite));
  const lift = raisable.filter((_, k) => gains[k]! > 0 && gains[k]! > 0.1 * most);
  const total = lift.reduce((sum, i) => sum + gains[raisable.indexOf(i)]!, 0);
  if (!lift.length || total < -v0) return null;
  const raised = (share: number): number[] =>
    base.map((b, j) => (lift.includes(j) ? Math.min(controls[j]!.high, b + share * (controls[j]!.high - b)) : b));
  let share = -v0 / total;
  const v1 = (await probe([raised(share)]))[0]?.[vz];
  if (v1 !== undefined && Number.isFinite(v1) && v1 - v0 > 1e-9) share *= -v0 / (v1 - v0);
  return raised(Math.min(1, Math.max(0, share)));
}
