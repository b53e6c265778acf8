// Mesh geoms drawn from their files: the artifact's STL, OBJ or MSH (GET /models/{model}/assets/{asset},
// named by /geometry), read with three's STL and OBJ loaders (MuJoCo's own binary MSH read here), and
// placed in the geom's frame as MuJoCo places the compiled mesh: scaled, then moved so that its centre
// of mass and axes of inertia are the geom's frame (MeshInfo: v -> conj(quat) · (scale ∘ v − pos)).
import * as THREE from 'three';
import { OBJLoader } from 'three/examples/jsm/loaders/OBJLoader.js';
import { STLLoader } from 'three/examples/jsm/loaders/STLLoader.js';
import { mergeGeometries, toCreasedNormals } from 'three/examples/jsm/utils/BufferGeometryUtils.js';
import type { MeshInfo } from '../api/emulator.gen';

export type MeshFormat = 'stl' | 'obj' | 'msh';

/** Faces meeting at more than this angle keep a sharp edge; below it, shading is smooth across them. */
const CREASE = Math.PI / 6;

/** The format of a mesh file by its extension (MuJoCo's mesh formats), or null. */
export function meshFormat(file: string): MeshFormat | null {
  const ext = file.toLowerCase().split('.').pop();
  return ext === 'stl' || ext === 'obj' || ext === 'msh' ? ext : null;
}

/** Positions alone (what every format has), as a non-indexed geometry. */
function positionsOnly(g: THREE.BufferGeometry): THREE.BufferGeometry {
  const flat = g.index ? g.toNonIndexed() : g;
  const out = new THREE.BufferGeometry();
  out.setAttribute('position', flat.getAttribute('position'));
  return out;
}

/** MuJoCo's binary MSH: four int32 counts (vertices, normals, texture coordinates, faces), then the
 * float32 vertices, normals and texture coordinates, then the int32 faces (three vertex indices each).
 * null for a file with no faces (MuJoCo would draw its convex hull). */
export function parseMsh(data: ArrayBuffer): THREE.BufferGeometry | null {
  if (data.byteLength < 16) throw new Error(`an MSH file has a 16-byte header; got ${data.byteLength} bytes`);
  const [nv = 0, nn = 0, nt = 0, nf = 0] = new Int32Array(data, 0, 4);
  const expected = 16 + 4 * (3 * nv + 3 * nn + 2 * nt + 3 * nf);
  if (nv < 0 || nn < 0 || nt < 0 || nf < 0 || expected !== data.byteLength)
    throw new Error(`an MSH file with ${nv} vertices, ${nn} normals, ${nt} texture coordinates and ${nf} faces has ${expected} bytes; got ${data.byteLength}`);
  if (nf === 0) return null;
  const vertices = new Float32Array(data, 16, 3 * nv);
  const faces = new Int32Array(data, 16 + 4 * (3 * nv + 3 * nn + 2 * nt), 3 * nf);
  if (faces.some((i) => i < 0 || i >= nv)) throw new Error(`an MSH face names a vertex outside 0..${nv - 1}`);
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(vertices.slice(), 3));
  g.setIndex(new THREE.BufferAttribute(Uint32Array.from(faces), 1));
  return positionsOnly(g);
}

/** The triangles of a mesh file (positions in the file's frame), or null when it has none. */
export function parseMesh(data: ArrayBuffer, format: MeshFormat): THREE.BufferGeometry | null {
  if (format === 'msh') return parseMsh(data);
  if (format === 'stl') return positionsOnly(new STLLoader().parse(data));
  // an OBJ may hold several objects and groups: MuJoCo takes them as one mesh
  const parts: THREE.BufferGeometry[] = [];
  new OBJLoader().parse(new TextDecoder().decode(data)).traverse((o) => {
    if (o instanceof THREE.Mesh) parts.push(positionsOnly(o.geometry as THREE.BufferGeometry));
  });
  if (!parts.length) return null;
  return parts.length === 1 ? parts[0]! : mergeGeometries(parts);
}

/** The geometry moved from the file's frame into the geom's (in place), with normals for lighting. */
export function placeMesh(g: THREE.BufferGeometry, mesh: MeshInfo): THREE.BufferGeometry {
  const [sx = 1, sy = 1, sz = 1] = mesh.scale;
  const [px = 0, py = 0, pz = 0] = mesh.pos;
  const [w = 1, x = 0, y = 0, z = 0] = mesh.quat;
  g.scale(sx, sy, sz);
  g.translate(-px, -py, -pz);
  g.applyQuaternion(new THREE.Quaternion(x, y, z, w).invert());
  const shaded = toCreasedNormals(g, CREASE);
  shaded.computeBoundingBox();
  shaded.computeBoundingSphere();
  return shaded;
}

/** Fetches a mesh's file (the asset's bytes). */
export type FetchAsset = (asset: string) => Promise<ArrayBuffer>;

/** Loads mesh geoms' geometries in their geom's frame; null for a mesh without a file or with no
 * triangles. Each file is fetched, read and placed once per placement; callers get their own copy. */
export class MeshFiles {
  private readonly cache = new Map<string, Promise<THREE.BufferGeometry | null>>();

  constructor(private readonly fetchAsset: FetchAsset) {}

  async geometry(mesh: MeshInfo): Promise<THREE.BufferGeometry | null> {
    const asset = mesh.asset;
    const format = asset ? meshFormat(asset) : null;
    if (!asset || !format) return null;
    const key = JSON.stringify([asset, mesh.scale, mesh.pos, mesh.quat]);
    let found = this.cache.get(key);
    if (!found) {
      found = this.fetchAsset(asset).then((bytes) => {
        const g = parseMesh(bytes, format);
        return g && placeMesh(g, mesh);
      });
      found.catch(() => this.cache.delete(key)); // a failed fetch is tried again next time
      this.cache.set(key, found);
    }
    const g = await found;
    return g ? g.clone() : null;
  }
}
