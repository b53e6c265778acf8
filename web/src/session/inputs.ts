// Keyboard and slider driving, derived from the manifest's controls alone: each control gets a key
// pair (held: the control's high or low end; released: back to its slider's value). Throttle-like
// controls (thrust, jet, gas) get the up/down arrows, steering-like ones (steer, yaw, turn) left/right,
// the rest W/S, D/A, E/Q, I/K, L/J, O/U in order. External forces (a model such as pendulum-force has
// pushes besides its motors) get sliders and the key pairs left after the controls.
import type { ControlInfo, ForceInfo } from '../api/emulator.gen';

export type InputKind = 'control' | 'force';

export interface Binding {
  index: number; // within its kind: the control's or the force's place in the manifest
  kind: InputKind;
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

type Input = Pick<ControlInfo | ForceInfo, 'name' | 'low' | 'high'>;

/** Key and slider bindings of a model's controls, then of its external forces (in the manifest's order). */
export function bindingsFor(controls: Input[], forces: Input[] = []): Binding[] {
  const taken = new Set<string>();
  const inputs = [...controls.map((c, i) => ({ c, i, kind: 'control' as const })), ...forces.map((c, i) => ({ c, i, kind: 'force' as const }))];
  const out: (Binding | null)[] = inputs.map(() => null);
  const binding = (j: number, hi: string, lo: string): Binding => {
    const { c, i, kind } = inputs[j]!;
    return { index: i, kind, name: c.name, low: c.low, high: c.high, rest: restValue(c.low, c.high), keyHigh: hi, keyLow: lo };
  };
  const make = (j: number, _c: Input, hi: string, lo: string): void => {
    out[j] = binding(j, hi, lo);
    taken.add(hi).add(lo);
  };
  const throttle = controls.findIndex((c) => THROTTLE.test(c.name));
  if (throttle >= 0) make(throttle, controls[throttle]!, 'ArrowUp', 'ArrowDown');
  const steer = controls.findIndex((c, i) => i !== throttle && STEER.test(c.name));
  if (steer >= 0) make(steer, controls[steer]!, 'ArrowLeft', 'ArrowRight'); // positive steering turns left
  const free = PAIRS.filter(([a, b]) => !taken.has(a) && !taken.has(b));
  inputs.forEach(({ c }, j) => {
    if (out[j]) return;
    const pair = free.shift();
    if (pair) make(j, c, pair[0], pair[1]);
    else out[j] = binding(j, '', '');
  });
  return out as Binding[];
}

/** What a control does, from the manifest's words: its label, what a value of 1 applies (gain and
 * unit) and what a positive value does; empty when the manifest does not say. */
export function controlMeaning(c: Pick<ControlInfo, 'label' | 'unit' | 'gain' | 'sign'>, withSign = true): string {
  const parts: string[] = [];
  if (c.label) parts.push(c.label);
  if (c.unit) parts.push(c.gain != null ? `1 = ${Number(c.gain.toPrecision(3))} ${c.unit}` : `in ${c.unit}`);
  if (c.sign && withSign) parts.push(/^positive/i.test(c.sign) ? c.sign : `positive: ${c.sign}`);
  return parts.join('; ');
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

  /** The control vector (U) and the force vector (F) to send. */
  split(): { controls: number[]; forces: number[] } {
    const v = this.values();
    return {
      controls: v.filter((_, i) => this.bindings[i]!.kind === 'control'),
      forces: v.filter((_, i) => this.bindings[i]!.kind === 'force'),
    };
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
