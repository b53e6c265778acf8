import * as THREE from 'three';
import { describe, expect, it } from 'vitest';
import type { GeomInfo, MeshInfo } from '../src/api/emulator.gen';
import { appearance, solidMaterial } from '../src/scene/materials';
import { MeshFiles, meshFormat, parseMesh, parseMsh, placeMesh } from '../src/scene/meshes';
import KNOB from '../../tests/data/tinybot/assets/knob.obj?raw';

const bytes = (text: string): ArrayBuffer => new TextEncoder().encode(text).buffer as ArrayBuffer;

// A lopsided wedge scaled by (2, 1, 0.5), and where MuJoCo 4.0 puts its vertices once compiled (mesh_vert;
// tests/services/emulator/test_scene.py checks the service's placement against MuJoCo the same way).
const WEDGE_OBJ = 'v 0 0 0\nv 1 0 0\nv 0 2 0\nv 0 0 3\nv 1 2 3\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 5\nf 2 5 4\nf 3 4 5\n';
const WEDGE: MeshInfo = { name: 'wedge', asset: 'w.obj', scale: [2, 1, 0.5], pos: [0.833333, 0.833333, 0.625], quat: [0.562708, 0.303512, -0.732744, 0.233081] };
const WEDGE_COMPILED = [
  [-0.2997, 0, 1.2999],
  [-0.6647, -1.4142, -0.0664],
  [-0.6647, 1.4142, -0.0664],
  [1.1495, 0, 0.9128],
  [0.4196, 0, -1.8198],
];

function points(g: THREE.BufferGeometry): number[][] {
  const p = g.getAttribute('position');
  return Array.from({ length: p.count }, (_, i) => [p.getX(i), p.getY(i), p.getZ(i)]);
}

/** A binary STL of triangles (each three [x, y, z]). */
function binaryStl(triangles: number[][][]): ArrayBuffer {
  const buf = new ArrayBuffer(84 + 50 * triangles.length);
  const v = new DataView(buf);
  v.setUint32(80, triangles.length, true);
  triangles.forEach((t, i) => t.flat().forEach((x, j) => v.setFloat32(84 + 50 * i + 12 + 4 * j, x, true)));
  return buf;
}

/** MuJoCo's MSH: counts (vertices, normals, texture coordinates, faces), then the arrays. */
function msh(vertices: number[], faces: number[]): ArrayBuffer {
  const buf = new ArrayBuffer(16 + 4 * (vertices.length + faces.length));
  new Int32Array(buf, 0, 4).set([vertices.length / 3, 0, 0, faces.length / 3]);
  new Float32Array(buf, 16, vertices.length).set(vertices);
  new Int32Array(buf, 16 + 4 * vertices.length, faces.length).set(faces);
  return buf;
}

describe('mesh files', () => {
  it('knows MuJoCo mesh formats by extension', () => {
    expect(['a.STL', 'b.obj', 'c.msh', 'd.png', 'e'].map(meshFormat)).toEqual(['stl', 'obj', 'msh', null, null]);
  });

  it('reads an OBJ (the test model folder knob: a cube of 12 triangles) and merges its objects', () => {
    const knob = parseMesh(bytes(KNOB), 'obj')!;
    expect(knob.getAttribute('position').count).toBe(36);
    knob.computeBoundingBox();
    knob.boundingBox!.min.toArray().forEach((v) => expect(v).toBeCloseTo(-0.1, 6));
    const two = parseMesh(bytes(`o a\n${WEDGE_OBJ}o b\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf 6 7 8\n`), 'obj')!;
    expect(two.getAttribute('position').count).toBe(3 * 7);
    expect(parseMesh(bytes('v 0 0 0\n'), 'obj')).toBeNull();
  });

  it('reads binary and ASCII STL', () => {
    const tri = [
      [0, 0, 0],
      [1, 0, 0],
      [0, 1, 0],
    ];
    expect(points(parseMesh(binaryStl([tri, tri]), 'stl')!)).toHaveLength(6);
    const ascii = `solid t\nfacet normal 0 0 1\nouter loop\n${tri.map((p) => `vertex ${p.join(' ')}`).join('\n')}\nendloop\nendfacet\nendsolid t\n`;
    expect(points(parseMesh(bytes(ascii), 'stl')!)).toEqual(tri);
  });

  it("reads MuJoCo's MSH, and names what is wrong with a bad one", () => {
    const g = parseMsh(msh([0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 1, 2, 0, 1, 3]))!;
    expect(points(g)).toEqual([
      [0, 0, 0],
      [1, 0, 0],
      [0, 1, 0],
      [0, 0, 0],
      [1, 0, 0],
      [0, 0, 1],
    ]);
    expect(parseMsh(msh([0, 0, 0], []))).toBeNull();
    expect(() => parseMsh(new ArrayBuffer(8))).toThrow(/16-byte header/);
    expect(() => parseMsh(msh([0, 0, 0], [0, 1, 2]))).toThrow(/outside 0\.\.0/);
    expect(() => parseMsh(msh([0, 0, 0, 1, 1, 1], [0, 1, 1]).slice(0, 30))).toThrow(/has 52 bytes; got 30/);
  });

  it('places a file where MuJoCo puts the compiled mesh (scaled, centred, turned onto its axes of inertia)', () => {
    const placed = placeMesh(parseMesh(bytes(WEDGE_OBJ), 'obj')!, WEDGE);
    const got = points(placed);
    for (const want of WEDGE_COMPILED) {
      const nearest = Math.min(...got.map((p) => Math.hypot(p[0]! - want[0]!, p[1]! - want[1]!, p[2]! - want[2]!)));
      expect(nearest).toBeLessThan(1e-3);
    }
    expect(placed.getAttribute('normal').count).toBe(got.length); // lit
  });

  it('fetches and reads a file once, gives each view its own copy, and retries a failed fetch', async () => {
    let calls = 0;
    let fail = true;
    const files = new MeshFiles(async (asset) => {
      calls += 1;
      if (asset === 'flaky.obj' && fail) throw new Error('offline');
      return bytes(WEDGE_OBJ);
    });
    const [a, b] = await Promise.all([files.geometry(WEDGE), files.geometry(WEDGE)]);
    expect(calls).toBe(1);
    expect(a).not.toBe(b);
    expect(points(a!)).toEqual(points(b!));
    expect(await files.geometry({ ...WEDGE, asset: null })).toBeNull();
    expect(await files.geometry({ ...WEDGE, asset: 'texture.png' })).toBeNull();
    await expect(files.geometry({ ...WEDGE, asset: 'flaky.obj' })).rejects.toThrow('offline');
    fail = false;
    expect(await files.geometry({ ...WEDGE, asset: 'flaky.obj' })).not.toBeNull();
  });
});

describe('geom appearance', () => {
  const geom = (rgba: number[], material?: GeomInfo['material']): GeomInfo => ({ name: 'g', type: 'box', size: [1, 1, 1], pos: [0, 0, 0], quat: [1, 0, 0, 0], rgba, material });
  const red = { name: 'red', rgba: [0.9, 0.1, 0.1, 1], emission: 0.3, specular: 0.5, shininess: 1, reflectance: 0.2 };

  it("is the material's when the geom keeps MuJoCo's default rgba", () => {
    const a = appearance(geom([0.5, 0.5, 0.5, 1], red));
    expect(a).toEqual({ rgba: [0.9, 0.1, 0.1, 1], emission: 0.3, specular: 0.5, shininess: 1, reflectance: 0.2 });
  });

  it("is the geom's own rgba when it sets one, or has no material", () => {
    expect(appearance(geom([0, 1, 0, 0.5], red)).rgba).toEqual([0, 1, 0, 0.5]);
    expect(appearance(geom([0.5, 0.5, 0.5, 1]))).toEqual({ rgba: [0.5, 0.5, 0.5, 1], emission: 0, specular: 0.5, shininess: 0.5, reflectance: 0 });
  });

  it('becomes a three.js material: colour, transparency, glow and surface', () => {
    const m = solidMaterial(appearance(geom([0.5, 0.5, 0.5, 1], red)));
    expect(m.roughness).toBeCloseTo(0.2);
    expect(m.metalness).toBeCloseTo(0.29);
    expect(m.emissive.r).toBeGreaterThan(0);
    expect(m.transparent).toBe(false);
    const plain = solidMaterial(appearance(geom([0.5, 0.5, 0.5, 0.4])));
    expect([plain.roughness, plain.metalness, plain.transparent, plain.opacity]).toEqual([0.6, 0.15, true, 0.4]);
  });
});
