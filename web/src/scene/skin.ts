// A MuJoCo skin (MJCF <skin>, GET /models/{model}/geometry `skins`): a triangle surface whose vertices
// follow bodies, drawn smooth over them (the dolphin's body over its 23 nodes). Vertices are placed as
// MuJoCo's mjv_updateSkin places them: for each bone, q = quat ⊗ bindquat⁻¹ and
// v' += w · (R(q) v + p − R(q) bindpos), (p, quat) the bone's body pose; then each vertex is pushed
// `inflate` metres along its normal (the mean of its faces' normals).
import * as THREE from 'three';
import type { SkinInfo } from '../api/emulator.gen';
import type { Pose } from './interp';

/** Rotate v (3) by the unit quaternion [w, x, y, z] into out (3). */
function rotate(q: readonly number[], v: readonly number[], out: number[]): void {
  const [w, x, y, z] = q as [number, number, number, number];
  const [vx, vy, vz] = v as [number, number, number];
  // t = 2 q_vec × v; v' = v + w t + q_vec × t
  const tx = 2 * (y * vz - z * vy);
  const ty = 2 * (z * vx - x * vz);
  const tz = 2 * (x * vy - y * vx);
  out[0] = vx + w * tx + (y * tz - z * ty);
  out[1] = vy + w * ty + (z * tx - x * tz);
  out[2] = vz + w * tz + (x * ty - y * tx);
}

/** [w, x, y, z] product a ⊗ b. */
function multiply(a: readonly number[], b: readonly number[]): number[] {
  const [w1, x1, y1, z1] = a as [number, number, number, number];
  const [w2, x2, y2, z2] = b as [number, number, number, number];
  return [
    w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
    w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
    w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
  ];
}

/**
 * The skin's vertex positions (V·3, MuJoCo's world frame) at body poses, before inflation; written into
 * `out` when given. Poses are [x, y, z, qw, qx, qy, qz] per body, in the order of `bodies`.
 */
export function skinVertices(skin: SkinInfo, poses: Pose[], out?: Float32Array): Float32Array {
  const v = skin.vertices;
  const pos = out ?? new Float32Array(v.length);
  pos.fill(0);
  const r = [0, 0, 0];
  const b = [0, 0, 0];
  for (const bone of skin.bones) {
    const p = poses[bone.body];
    if (!p) continue;
    const bq = bone.bindquat;
    const q = multiply([p[3]!, p[4]!, p[5]!, p[6]!], [bq[0]!, -bq[1]!, -bq[2]!, -bq[3]!]);
    rotate(q, bone.bindpos, b);
    const sx = p[0]! - b[0]!;
    const sy = p[1]! - b[1]!;
    const sz = p[2]! - b[2]!;
    bone.vertices.forEach((i, k) => {
      const w = bone.weights[k] ?? 0;
      rotate(q, [v[3 * i]!, v[3 * i + 1]!, v[3 * i + 2]!], r);
      pos[3 * i] = pos[3 * i]! + w * (r[0]! + sx);
      pos[3 * i + 1] = pos[3 * i + 1]! + w * (r[1]! + sy);
      pos[3 * i + 2] = pos[3 * i + 2]! + w * (r[2]! + sz);
    });
  }
  return pos;
}

/** A skin drawn as one smooth-shaded mesh, moved by `update(poses)`. */
export class SkinView {
  readonly mesh: THREE.Mesh;
  private readonly bare: Float32Array;
  private readonly geometry = new THREE.BufferGeometry();

  constructor(
    readonly skin: SkinInfo,
    material: THREE.Material,
  ) {
    this.bare = new Float32Array(skin.vertices.length);
    this.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(skin.vertices.length), 3));
    this.geometry.setIndex(skin.faces);
    this.mesh = new THREE.Mesh(this.geometry, material);
    this.mesh.name = `skin:${skin.name}`;
    this.mesh.userData.skin = skin.name;
  }

  /** Place the vertices at these body poses, then inflate them along the smooth normals. */
  update(poses: Pose[]): void {
    skinVertices(this.skin, poses, this.bare);
    const attr = this.geometry.getAttribute('position') as THREE.BufferAttribute;
    const out = attr.array as Float32Array;
    out.set(this.bare);
    attr.needsUpdate = true;
    this.geometry.computeVertexNormals();
    const inflate = this.skin.inflate ?? 0;
    if (inflate) {
      const n = this.geometry.getAttribute('normal').array as Float32Array;
      for (let i = 0; i < out.length; i++) out[i] = this.bare[i]! + inflate * n[i]!;
    }
    this.geometry.computeBoundingBox();
    this.geometry.computeBoundingSphere();
  }

  dispose(): void {
    this.geometry.dispose();
  }
}
