import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { SkinView, skinVertices } from '../src/scene/skin';
import type { SkinInfo } from '../src/api/emulator.gen';

const quarterZ = [Math.SQRT1_2, 0, 0, Math.SQRT1_2]; // 90° about z

/** Two vertices: one on body 0, one shared half and half by bodies 0 and 1. */
const skin: SkinInfo = {
  name: 's',
  rgba: [1, 1, 1, 1],
  inflate: 0,
  vertices: [1, 0, 0, 0, 1, 0],
  faces: [],
  bones: [
    { body: 0, bindpos: [0, 0, 0], bindquat: [1, 0, 0, 0], vertices: [0, 1], weights: [1, 0.5] },
    { body: 1, bindpos: [0, 1, 0], bindquat: [1, 0, 0, 0], vertices: [1], weights: [0.5] },
  ],
};

describe('skin vertices (MuJoCo mjv_updateSkin)', () => {
  it('are the bind positions at the bind poses', () => {
    const v = skinVertices(skin, [
      [0, 0, 0, 1, 0, 0, 0],
      [0, 1, 0, 1, 0, 0, 0],
    ]);
    expect([...v]).toEqual([1, 0, 0, 0, 1, 0]);
  });

  it('turn and move with their bones, blended by weight', () => {
    const v = skinVertices(skin, [
      [2, 0, 0, ...quarterZ], // body 0 moved to x = 2 and turned a quarter about z
      [0, 1, 5, 1, 0, 0, 0], // body 1 lifted 5 up
    ] as number[][]);
    // vertex 0 on body 0: (1, 0, 0) turned to (0, 1, 0), then moved by (2, 0, 0)
    expect(v[0]).toBeCloseTo(2, 6);
    expect(v[1]).toBeCloseTo(1, 6);
    // vertex 1: half of body 0's (0, 1, 0) -> (-1, 0, 0) + (2, 0, 0), half of body 1's (0, 1, 5)
    expect(v[3]).toBeCloseTo(0.5 * 1 + 0.5 * 0, 6);
    expect(v[4]).toBeCloseTo(0.5 * 0 + 0.5 * 1, 6);
    expect(v[5]).toBeCloseTo(0.5 * 5, 6);
  });

  it('honours a bind rotation: a bone bound turned follows its body relative to that turn', () => {
    const turned: SkinInfo = {
      ...skin,
      vertices: [0, 1, 0],
      bones: [{ body: 0, bindpos: [0, 0, 0], bindquat: quarterZ, vertices: [0], weights: [1] }],
    };
    // the body at its bind attitude: the vertex where it was bound
    const close = (v: Float32Array): number[] => [...v].map((x) => Math.round(x * 1e6) / 1e6 + 0); // -0 -> 0
    expect(close(skinVertices(turned, [[0, 0, 0, ...quarterZ] as number[]]))).toEqual([0, 1, 0]);
    // the body back at the identity: the vertex turned back a quarter, (0, 1, 0) -> (1, 0, 0)
    expect(close(skinVertices(turned, [[0, 0, 0, 1, 0, 0, 0]]))).toEqual([1, 0, 0]);
  });

  it('a mesh of it is inflated along its normals and moves with update()', () => {
    const tri: SkinInfo = {
      name: 't',
      rgba: [1, 1, 1, 1],
      inflate: 0.1,
      vertices: [0, 0, 0, 1, 0, 0, 0, 1, 0],
      faces: [0, 1, 2],
      bones: [{ body: 0, bindpos: [0, 0, 0], bindquat: [1, 0, 0, 0], vertices: [0, 1, 2], weights: [1, 1, 1] }],
    };
    const view = new SkinView(tri, new THREE.MeshBasicMaterial());
    view.update([[0, 0, 3, 1, 0, 0, 0]]);
    const p = view.mesh.geometry.getAttribute('position').array as Float32Array;
    // lifted 3, pushed 0.1 along the face's normal (+z for this winding)
    expect([...p].filter((_, i) => i % 3 === 2).map((z) => +z.toFixed(5))).toEqual([3.1, 3.1, 3.1]);
    expect(view.mesh.geometry.boundingBox!.max.z).toBeCloseTo(3.1, 5);
    view.dispose();
  });
});
