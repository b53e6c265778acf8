// Keyboard and slider driving, derived from the manifest's controls alone: each control gets a key
// pair (held: the control's high or low end; released: back to its slider's value). Throttle-like
// controls (thrust, jet, gas) get the up/down arrows, steering-like ones (steer, yaw, turn) left/right,
// the rest W/S, D/A, E/Q, I/K, L/J, O/U in order.
import type { ControlInfo } from '../api/emulator.gen';

export interface Binding {
  index: number;
  name: string;
  low: number;
  high: number;
  rest: number; // the slider's starting value: 0 when in range, else the nearer end
  keyHigh: string; // KeyboardEvent.code
  keyLow: string;
}

const PAIRS: [string, string][] = [
  ['KeyW', 'KeyS'],
  ['KeyD', 'KeyA'],
  ['KeyE', 'KeyQ'],
  ['KeyI', 'KeyK'],
  ['KeyL', 'KeyJ'],
  ['KeyO', 'KeyU'],
  ['KeyT', 'KeyG'],
  ['KeyH', 'KeyF'],
];
const THROTTLE = /thrust|throttle|jet|gas|main|engine|drive/i;
const STEER = /steer|turn|yaw|rudder/i;

export function restValue(low: number, high: number): number {
  return Math.min(high, Math.max(low, 0));
}

export function bindingsFor(controls: ControlInfo[]): Binding[] {
  const taken = new Set<string>();
  const out: (Binding | null)[] = controls.map(() => null);
  const make = (i: number, c: ControlInfo, hi: string, lo: string): void => {
    out[i] = { index: i, name: c.name, low: c.low, high: c.high, rest: restValue(c.low, c.high), keyHigh: hi, keyLow: lo };
    taken.add(hi).add(lo);
  };
  const throttle = controls.findIndex((c) => THROTTLE.test(c.name));
  if (throttle >= 0) make(throttle, controls[throttle]!, 'ArrowUp', 'ArrowDown');
  const steer = controls.findIndex((c, i) => i !== throttle && STEER.test(c.name));
  if (steer >= 0) make(steer, controls[steer]!, 'ArrowLeft', 'ArrowRight'); // positive steering turns left
  const free = PAIRS.filter(([a, b]) => !taken.has(a) && !taken.has(b));
  controls.forEach((c, i) => {
    if (out[i]) return;
    const pair = free.shift();
    if (pair) make(i, c, pair[0], pair[1]);
    else out[i] = { index: i, name: c.name, low: c.low, high: c.high, rest: restValue(c.low, c.high), keyHigh: '', keyLow: '' };
  });
  return out as Binding[];
}

/** A key code as printed on the key: 'KeyW' -> 'W', 'ArrowUp' -> '↑'. */
export function keyLabel(code: string): string {
  const arrows: Record<string, string> = { ArrowUp: '↑', ArrowDown: '↓', ArrowLeft: '←', ArrowRight: '→' };
  return arrows[code] ?? code.replace(/^Key/, '');
}

/** Slider values plus held keys -> the control vector. */
export class Drive {
  readonly base: number[];
  private readonly held = new Set<string>();

  constructor(readonly bindings: Binding[]) {
    this.base = bindings.map((b) => b.rest);
  }

  /** True when the key belongs to a control (the caller then prevents its default). */
  press(code: string): boolean {
    if (!this.bindings.some((b) => b.keyHigh === code || b.keyLow === code)) return false;
    this.held.add(code);
    return true;
  }

  release(code: string): boolean {
    return this.held.delete(code);
  }

  releaseAll(): void {
    this.held.clear();
  }

  values(): number[] {
    return this.bindings.map((b, i) => {
      const hi = b.keyHigh !== '' && this.held.has(b.keyHigh);
      const lo = b.keyLow !== '' && this.held.has(b.keyLow);
      if (hi && !lo) return b.high;
      if (lo && !hi) return b.low;
      return this.base[i] ?? b.rest;
    });
  }
}
