// Frames between super-steps: states come every Δt (0.5 s for the default emulators); the view shows
// poses at the display rate, interpolated between the two states around the render time (positions
// linearly, orientations by slerp). A pose is [x, y, z, qw, qx, qy, qz].

export type Pose = number[];

/** Spherical linear interpolation of unit quaternions [w, x, y, z], the shorter way round. */
export function slerp(a: number[], b: number[], t: number): number[] {
  let [bw, bx, by, bz] = [b[0] ?? 1, b[1] ?? 0, b[2] ?? 0, b[3] ?? 0];
  const [aw, ax, ay, az] = [a[0] ?? 1, a[1] ?? 0, a[2] ?? 0, a[3] ?? 0];
  let dot = aw * bw + ax * bx + ay * by + az * bz;
  if (dot < 0) {
    [bw, bx, by, bz] = [-bw, -bx, -by, -bz];
    dot = -dot;
  }
  let ka: number;
  let kb: number;
  if (dot > 0.9995) {
    ka = 1 - t;
    kb = t;
  } else {
    const theta = Math.acos(Math.min(1, dot));
    const s = Math.sin(theta);
    ka = Math.sin((1 - t) * theta) / s;
    kb = Math.sin(t * theta) / s;
  }
  const q = [ka * aw + kb * bw, ka * ax + kb * bx, ka * ay + kb * by, ka * az + kb * bz];
  const n = Math.hypot(q[0]!, q[1]!, q[2]!, q[3]!) || 1;
  return q.map((v) => v / n);
}

export function lerpPose(a: Pose, b: Pose, t: number): Pose {
  const p = [0, 1, 2].map((i) => (a[i] ?? 0) + ((b[i] ?? 0) - (a[i] ?? 0)) * t);
  return [...p, ...slerp(a.slice(3, 7), b.slice(3, 7), t)];
}

export function lerpPoses(a: Pose[], b: Pose[], t: number): Pose[] {
  return a.map((p, i) => lerpPose(p, b[i] ?? p, t));
}

interface Snapshot<T> {
  time: number;
  value: T;
}

/**
 * Timed snapshots, sampled at a render time that trails the newest snapshot by `delay` (one period),
 * so there is (almost) always a later snapshot to interpolate towards.
 */
export class SnapshotBuffer<T> {
  private items: Snapshot<T>[] = [];

  constructor(
    private readonly mix: (a: T, b: T, t: number) => T,
    private readonly capacity = 32,
  ) {}

  get size(): number {
    return this.items.length;
  }

  clear(): void {
    this.items = [];
  }

  push(time: number, value: T): void {
    const last = this.items[this.items.length - 1];
    if (last && time <= last.time) time = last.time + 1e-6;
    this.items.push({ time, value });
    if (this.items.length > this.capacity) this.items.shift();
  }

  /** The value at `time`: interpolated between neighbours, held at the ends. */
  sample(time: number): T | null {
    const items = this.items;
    if (!items.length) return null;
    const first = items[0]!;
    if (time <= first.time) return first.value;
    for (let i = 1; i < items.length; i++) {
      const b = items[i]!;
      if (time <= b.time) {
        const a = items[i - 1]!;
        return this.mix(a.value, b.value, (time - a.time) / (b.time - a.time));
      }
    }
    return items[items.length - 1]!.value;
  }
}

/**
 * Index and fraction of `t` in the increasing `times` (for replaying a trajectory): the segment
 * [times[i], times[i+1]] and how far along it t is; clamped to the ends.
 */
export function locate(times: number[], t: number): { i: number; f: number } {
  const n = times.length;
  if (n < 2 || t <= (times[0] ?? 0)) return { i: 0, f: 0 };
  if (t >= times[n - 1]!) return { i: Math.max(0, n - 2), f: 1 };
  let lo = 0;
  let hi = n - 1;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (times[mid]! <= t) lo = mid;
    else hi = mid;
  }
  const a = times[lo]!;
  const b = times[hi]!;
  return { i: lo, f: b > a ? (t - a) / (b - a) : 0 };
}
