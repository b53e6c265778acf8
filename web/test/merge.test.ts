import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { ModelView } from '../src/scene/model';
import type { GeomInfo, ModelGeometry } from '../src/api/emulator.gen';

const box = (name: string, x: number, rgba: number[]): GeomInfo => ({ name, type: 'box', size: [0.1, 0.1, 0.1], pos: [x, 0, 0], quat: [1, 0, 0, 0], rgba });
const red = [1, 0, 0, 1];
const blue = [0, 0, 1, 1];

function model(geoms: GeomInfo[], world: GeomInfo[] = []): ModelGeometry {
  return { model: 'm', version: 'v', bodies: [{ name: 'b', parent: 0, geoms }], world, rest_poses: [[0, 0, 0, 1, 0, 0, 0]], center: [0, 0, 0], extent: 1 };
}

function meshesOf(o: THREE.Object3D): THREE.Mesh[] {
  return o.children.filter((c): c is THREE.Mesh => c instanceof THREE.Mesh);
}

function boxOf(o: THREE.Object3D): THREE.Box3 {
  o.updateMatrixWorld(true);
  return new THREE.Box3().setFromObject(o);
}

describe("a body's geoms of one look", () => {
  const geoms = [box('a', 0, red), box('b', 1, red), box('c', 2, blue)];

  it('are one mesh in the same place: one draw call per look, not per geom', () => {
    const v = new ModelView(model(geoms));
    const meshes = meshesOf(v.bodies[0]!);
    expect(meshes).toHaveLength(2);
    const merged = meshes.find((m) => m.name === 'a+b')!;
    const b = boxOf(merged);
    expect(b.min.x).toBeCloseTo(-0.1);
    expect(b.max.x).toBeCloseTo(1.1);
    expect(boxOf(v.bodies[0]!).max.x).toBeCloseTo(2.1);
  });

  it("merge a ghost's faces and edges too, and the geoms fixed to the world", () => {
    const ghost = new ModelView(model(geoms), { ghost: true });
    const meshes = meshesOf(ghost.bodies[0]!);
    expect(meshes).toHaveLength(1);
    const edges = meshes[0]!.children.filter((c) => c instanceof THREE.LineSegments);
    expect(edges).toHaveLength(1);
    expect(boxOf(edges[0]!).max.x).toBeCloseTo(2.1);
    const withWorld = new ModelView(model([], [box('w1', 5, red), box('w2', 7, red)]));
    const fixed = withWorld.group.children.find((c) => c instanceof THREE.Group && !withWorld.bodies.includes(c as THREE.Group))!;
    expect(meshesOf(fixed)).toHaveLength(1);
  });
});
