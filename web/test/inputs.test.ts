import { describe, expect, it } from 'vitest';
import { bindingsFor, controlMeaning, Drive, keyLabel, restValue } from '../src/session/inputs';

const lander = [
  { name: 'main_jet', low: 0, high: 32.4 },
  { name: 'roll', low: -1, high: 1 },
  { name: 'pitch', low: -1, high: 1 },
  { name: 'yaw', low: -1, high: 1 },
];
const truck = [
  { name: 'steer', low: -10, high: 10 },
  { name: 'gas', low: -2, high: 5 },
];

describe('bindingsFor', () => {
  it('gives thrust the up/down arrows and steering left/right', () => {
    const b = bindingsFor(lander);
    expect(b.map((x) => x.keyHigh)).toEqual(['ArrowUp', 'KeyW', 'KeyD', 'ArrowLeft']);
    const t = bindingsFor(truck);
    expect(t[0]!.keyHigh).toBe('ArrowLeft');
    expect(t[1]!.keyHigh).toBe('ArrowUp');
  });

  it('binds every control of a model with many, distinct keys where it can', () => {
    const many = Array.from({ length: 12 }, (_, i) => ({ name: `torque${i}`, low: -2, high: 2 }));
    const b = bindingsFor(many);
    expect(b).toHaveLength(12);
    const keys = b.flatMap((x) => [x.keyHigh, x.keyLow]).filter(Boolean);
    expect(new Set(keys).size).toBe(keys.length);
    expect(b[11]!.keyHigh).toBe(''); // more controls than key pairs: slider only
  });

  it('rests at 0 when the range holds it, else at the nearer end', () => {
    expect(restValue(-1, 1)).toBe(0);
    expect(restValue(2, 5)).toBe(2);
    expect(restValue(-5, -2)).toBe(-2);
  });
});

describe('Drive', () => {
  it('held keys drive a control to its ends, releasing returns to the slider', () => {
    const d = new Drive(bindingsFor(truck));
    d.base[1] = 1.5;
    expect(d.values()).toEqual([0, 1.5]);
    expect(d.press('ArrowUp')).toBe(true);
    expect(d.press('KeyZ')).toBe(false);
    d.press('ArrowRight');
    expect(d.values()).toEqual([-10, 5]);
    d.release('ArrowUp');
    expect(d.values()).toEqual([-10, 1.5]);
    d.releaseAll();
    expect(d.values()).toEqual([0, 1.5]);
  });

  it('binds external forces after the controls and sends each vector apart', () => {
    const torques = [0, 1, 2].map((i) => ({ name: `torque${i}`, low: -2, high: 2 }));
    const pushes = [0, 1, 2].map((i) => ({ name: `push${i}`, low: -2, high: 2 }));
    const b = bindingsFor(torques, pushes);
    expect(b.map((x) => `${x.kind}:${x.index}`)).toEqual(['control:0', 'control:1', 'control:2', 'force:0', 'force:1', 'force:2']);
    const keys = b.flatMap((x) => [x.keyHigh, x.keyLow]);
    expect(new Set(keys).size).toBe(12);
    const d = new Drive(b);
    d.base[4] = 1.5;
    d.press(b[3]!.keyHigh);
    expect(d.split()).toEqual({ controls: [0, 0, 0], forces: [2, 1.5, 0] });
    expect(new Drive(bindingsFor(truck)).split().forces).toEqual([]);
  });

  it('labels keys as printed', () => {
    expect(keyLabel('KeyW')).toBe('W');
    expect(keyLabel('ArrowLeft')).toBe('←');
  });
});

describe('controlMeaning', () => {
  it("says what a control does in the manifest's words, or nothing", () => {
    expect(controlMeaning({ label: 'main jet', unit: 'N', gain: 10, sign: 'up along the body z axis' })).toBe('main jet; 1 = 10 N; positive: up along the body z axis');
    expect(controlMeaning({ label: 'steering', unit: 'N' })).toBe('steering; in N');
    expect(controlMeaning({})).toBe('');
    expect(controlMeaning({ label: 'roll jet', unit: 'N·m', gain: 0.25, sign: 'positive turns the lander about +x' })).toBe('roll jet; 1 = 0.25 N·m; positive turns the lander about +x');
    expect(controlMeaning({ label: 'roll jet', unit: 'N·m', gain: 0.25, sign: 'turns left' }, false)).toBe('roll jet; 1 = 0.25 N·m');
  });
});
