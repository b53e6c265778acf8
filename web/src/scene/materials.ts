// A geom's colour and surface from its MJCF, as MuJoCo's renderer chooses them: its material's rgba and
// lighting coefficients when it has a material, unless the geom has an rgba of its own (one other than
// MuJoCo's default 0.5 0.5 0.5 1), which wins.
import * as THREE from 'three';
import type { GeomInfo } from '../api/emulator.gen';

export interface Appearance {
  rgba: [number, number, number, number];
  emission: number;
  specular: number;
  shininess: number;
  reflectance: number;
}

const DEFAULT_RGBA = [0.5, 0.5, 0.5, 1];
const FLOAT_EPS = 1e-6; // the service rounds MuJoCo's float32 colours to 6 decimals

function rgbaOf(v: number[] | undefined, fallback: number[]): Appearance['rgba'] {
  const [r = fallback[0]!, g = fallback[1]!, b = fallback[2]!, a = fallback[3]!] = v ?? fallback;
  return [r, g, b, a];
}

/** What MuJoCo draws a geom with (see the module's text). */
export function appearance(g: GeomInfo): Appearance {
  const own = rgbaOf(g.rgba, DEFAULT_RGBA);
  const m = g.material;
  const isDefault = own.every((v, i) => Math.abs(v - DEFAULT_RGBA[i]!) < FLOAT_EPS);
  return {
    rgba: m && isDefault ? rgbaOf(m.rgba, [1, 1, 1, 1]) : own,
    emission: m?.emission ?? 0,
    specular: m?.specular ?? 0.5,
    shininess: m?.shininess ?? 0.5,
    reflectance: m?.reflectance ?? 0,
  };
}

/** A three.js material for an appearance: MuJoCo's shininess and reflectance as roughness and
 * metalness (its defaults give the dashboard's usual 0.6 and 0.15), emission as a glow of its colour. */
export function solidMaterial(look: Appearance): THREE.MeshStandardMaterial {
  const [r, g, b, a] = look.rgba;
  const color = new THREE.Color().setRGB(r, g, b, THREE.SRGBColorSpace);
  return new THREE.MeshStandardMaterial({
    color,
    emissive: color.clone().multiplyScalar(Math.min(1, Math.max(0, look.emission))),
    roughness: THREE.MathUtils.clamp(1 - 0.8 * look.shininess, 0.05, 1),
    metalness: THREE.MathUtils.clamp(0.15 + 0.7 * look.reflectance, 0, 1),
    transparent: a < 1,
    opacity: a,
    depthWrite: a >= 1,
  });
}
