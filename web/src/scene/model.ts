// A model drawn from its MJCF geometry (GET /models/{model}/geometry): one group per body, placed by
// world poses [x, y, z, qw, qx, qy, qz]; geoms are boxes, spheres, capsules, cylinders, ellipsoids,
// planes and meshes in their body's frame, with their MJCF colours and materials (materials.ts). A mesh
// is its bounding box until its file (STL, OBJ, MSH: meshes.ts) has loaded, then the file's triangles.
// Groups 0–2 are drawn (MuJoCo's defaults: collision geoms in group 3 stay hidden, visual-only geoms in
// group 2 give a model its look).
// A model's skins (MJCF <skin>: the dolphin's body surface) are smooth meshes over their bodies (skin.ts),
// placed with the bodies by setPoses.
// A "ghost" is the same model as a translucent outline in one colour (the MuJoCo twin, a goal).
// A body's geoms of one look are merged into one mesh (mergeByLook): every draw call has a fixed cost,
// which in software WebGL was a fifth of a frame for a lander and its ghost (60 draws).
import * as THREE from 'three';
import { mergeGeometries } from 'three/addons/utils/BufferGeometryUtils.js';
import type { GeomInfo, ModelGeometry } from '../api/emulator.gen';
import type { Pose } from './interp';
import { appearance, solidMaterial } from './materials';
import type { MeshFiles } from './meshes';
import { SkinView } from './skin';
import { softwareRendering } from './viewer';

export interface Look {
  ghost?: boolean;
  color?: number; // a ghost's colour
  opacity?: number; // a ghost's faces
  edgeOpacity?: number; // a ghost's outline (0.9)
}

const HIDDEN_GROUP = 3;

function shape(g: GeomInfo, ghost: boolean): THREE.BufferGeometry | null {
  const [a = 0.05, b = 0.05, c = 0.05] = g.size;
  // software WebGL pays for every vertex each frame: rounder shapes cost the lander 4-5 fps there
  const round = ghost || softwareRendering() ? 12 : 28;
  switch (g.type) {
    case 'box':
    case 'mesh':
      return new THREE.BoxGeometry(2 * a, 2 * b, 2 * c);
    case 'sphere':
      return new THREE.SphereGeometry(a, round, round / 2 + 2);
    case 'ellipsoid':
      return new THREE.SphereGeometry(1, round, round / 2 + 2).scale(a, b, c);
    case 'capsule': // three's capsule and cylinder run along y; MuJoCo's along the geom's z
      return new THREE.CapsuleGeometry(a, 2 * b, 6, round / 2 + 4).rotateX(Math.PI / 2);
    case 'cylinder':
      return new THREE.CylinderGeometry(a, a, 2 * b, round).rotateX(Math.PI / 2);
    default:
      return null; // planes are the ground (the viewer draws it), other types are not drawn
  }
}

function setPose(o: THREE.Object3D, p: number[]): void {
  o.position.set(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0);
  o.quaternion.set(p[4] ?? 0, p[5] ?? 0, p[6] ?? 0, p[3] ?? 1); // [w,x,y,z] -> three's (x,y,z,w)
}

/** Which mesh geoms were drawn from their files, and which files could not be (with why). */
export interface MeshesDrawn {
  drawn: THREE.Mesh[];
  failed: { geom: string; reason: string }[];
}

export class ModelView {
  readonly group = new THREE.Group();
  readonly bodies: THREE.Group[];
  /** The model's skins, drawn over its bodies. */
  readonly skins: SkinView[];
  /** The height of the model's own floor (a plane fixed to the world), if it has one. */
  readonly floorZ: number | null = null;
  /** Settles once every mesh geom with a file has its file's triangles (or kept its box). */
  readonly meshes: Promise<MeshesDrawn>;
  private readonly faces: THREE.Material | null = null;
  private readonly edges: THREE.LineBasicMaterial | null = null;
  private readonly loading: Promise<void>[] = [];
  private readonly drawn: MeshesDrawn = { drawn: [], failed: [] };
  private disposed = false;

  /** `files`: where mesh geoms' files come from (without it, a mesh stays its bounding box). */
  constructor(
    readonly geometry: ModelGeometry,
    readonly look: Look = {},
    private readonly files: MeshFiles | null = null,
  ) {
    if (look.ghost) {
      const color = new THREE.Color(look.color ?? 0x9be7ff);
      this.faces = new THREE.MeshBasicMaterial({ color, transparent: true, opacity: look.opacity ?? 0.22, depthWrite: false });
      this.edges = new THREE.LineBasicMaterial({ color, transparent: true, opacity: look.edgeOpacity ?? 0.9 });
    }
    this.bodies = geometry.bodies.map((body) => {
      const g = new THREE.Group();
      g.name = body.name;
      for (const geom of body.geoms) {
        const mesh = this.mesh(geom);
        if (mesh) g.add(mesh);
      }
      mergeByLook(g);
      this.group.add(g);
      return g;
    });
    if (!look.ghost) {
      const fixed = new THREE.Group(); // what is fixed to the world
      fixed.name = 'fixed';
      fixed.userData.shadowApart = true; // its contact shadow is not the moving bodies' (viewer.ts)
      for (const geom of geometry.world) {
        if (geom.type === 'plane') {
          if (this.floorZ === null || geom.pos[2]! < this.floorZ) this.floorZ = geom.pos[2] ?? 0;
          continue;
        }
        const mesh = this.mesh(geom);
        if (mesh) fixed.add(mesh);
      }
      mergeByLook(fixed);
      this.group.add(fixed);
    }
    this.skins = (geometry.skins ?? []).map((skin) => {
      const [r = 0.5, g = 0.5, b = 0.5, a = 1] = skin.rgba;
      const material =
        this.faces ??
        solidMaterial({ rgba: [r, g, b, a], emission: 0, specular: 0.5, shininess: 0.6, reflectance: 0 });
      if (!this.faces) (material as THREE.MeshStandardMaterial).side = THREE.DoubleSide;
      const view = new SkinView(skin, material);
      view.mesh.castShadow = !look.ghost;
      view.mesh.renderOrder = look.ghost ? 2 : 0;
      this.group.add(view.mesh);
      return view;
    });
    this.setPoses(geometry.rest_poses);
    this.meshes = Promise.all(this.loading).then(() => this.drawn);
  }

  private mesh(geom: GeomInfo): THREE.Object3D | null {
    if (geom.group !== undefined && geom.group >= HIDDEN_GROUP) return null;
    const s = shape(geom, !!this.look.ghost);
    if (!s) return null;
    let obj: THREE.Object3D;
    if (this.faces && this.edges) {
      const mesh = new THREE.Mesh(s, this.faces);
      mesh.renderOrder = 2;
      mesh.add(new THREE.LineSegments(new THREE.EdgesGeometry(s, 25), this.edges));
      obj = mesh;
    } else {
      const mesh = new THREE.Mesh(s, solidMaterial(appearance(geom)));
      mesh.castShadow = true;
      mesh.receiveShadow = true;
      obj = mesh;
    }
    obj.name = geom.name;
    setPose(obj, [...geom.pos, ...geom.quat]);
    if (geom.mesh?.asset && this.files && obj instanceof THREE.Mesh) this.loading.push(this.fromFile(obj, geom));
    // a geom drawn from a file keeps a mesh of its own (its triangles replace its box when they load)
    else obj.userData.look = this.faces ? 'ghost' : JSON.stringify(appearance(geom));
    return obj;
  }

  /** Replaces a mesh geom's box by its file's triangles once they have loaded. */
  private async fromFile(obj: THREE.Mesh, geom: GeomInfo): Promise<void> {
    try {
      const g = await this.files!.geometry(geom.mesh!);
      if (!g) return;
      if (this.disposed) {
        g.dispose();
        return;
      }
      const box = obj.geometry as THREE.BufferGeometry;
      obj.geometry = g;
      box.dispose();
      for (const child of obj.children) {
        if (child instanceof THREE.LineSegments) {
          child.geometry.dispose();
          child.geometry = new THREE.EdgesGeometry(g, 25);
        }
      }
      obj.userData.meshFile = geom.mesh!.asset;
      this.drawn.drawn.push(obj);
    } catch (e) {
      this.drawn.failed.push({ geom: geom.name, reason: e instanceof Error ? e.message : String(e) });
    }
  }

  setPoses(poses: Pose[]): void {
    poses.forEach((p, i) => {
      const b = this.bodies[i];
      if (b) setPose(b, p);
    });
    for (const skin of this.skins ?? []) skin.update(poses);
  }

  /** The root body (the first one): what a camera follows and a trail traces. */
  get root(): THREE.Group | null {
    return this.bodies[0] ?? null;
  }

  /** The moving bodies and skins (without what is fixed to the world), for framing. */
  get moving(): THREE.Object3D[] {
    return [...this.bodies, ...this.skins.map((s) => s.mesh)];
  }

  set visible(v: boolean) {
    this.group.visible = v;
  }

  get visible(): boolean {
    return this.group.visible;
  }

  dispose(): void {
    this.disposed = true;
    for (const skin of this.skins) skin.dispose();
    this.group.traverse((o) => {
      if (o instanceof THREE.Mesh || o instanceof THREE.LineSegments) {
        o.geometry.dispose();
        if (!this.faces) (o.material as THREE.Material).dispose();
      }
    });
    this.faces?.dispose();
    this.edges?.dispose();
    this.group.removeFromParent();
  }
}

/**
 * Merges the meshes directly under `group` that share a look (`userData.look`) into one mesh, in the
 * group's frame; a ghost's edges (a mesh's LineSegments child) merge with it into one set of lines.
 * Each look keeps the first mesh's material.
 */
function mergeByLook(group: THREE.Group): void {
  const byLook = new Map<string, THREE.Mesh[]>();
  for (const o of group.children) {
    const look = o.userData.look as string | undefined;
    if (look === undefined || !(o instanceof THREE.Mesh)) continue;
    byLook.set(look, [...(byLook.get(look) ?? []), o]);
  }
  for (const meshes of byLook.values()) {
    if (meshes.length < 2) continue;
    const first = meshes[0]!;
    const placed = (g: THREE.BufferGeometry, m: THREE.Mesh) => {
      m.updateMatrix();
      return g.clone().applyMatrix4(m.matrix);
    };
    const faces = mergeGeometries(meshes.map((m) => placed(m.geometry, m)));
    const lines = meshes.map((m) => m.children.find((c): c is THREE.LineSegments => c instanceof THREE.LineSegments));
    if (!faces) continue; // geometries that cannot be merged (different attributes): kept as they are
    const merged = new THREE.Mesh(faces, first.material);
    merged.castShadow = first.castShadow;
    merged.receiveShadow = first.receiveShadow;
    merged.renderOrder = first.renderOrder;
    merged.name = meshes.map((m) => m.name).join('+');
    if (lines.every((l) => l)) {
      const edges = mergeGeometries(lines.map((l, i) => placed(l!.geometry, meshes[i]!)));
      if (edges) merged.add(new THREE.LineSegments(edges, lines[0]!.material));
    }
    for (const m of meshes) {
      m.removeFromParent();
      m.geometry.dispose();
      for (const c of m.children) if (c instanceof THREE.LineSegments) c.geometry.dispose();
      if (m.material !== first.material) (m.material as THREE.Material).dispose();
    }
    group.add(merged);
  }
}

/**
 * The height of the ground for a model: its own floor if it has one; else just below the lowest point
 * of what is drawn at the given poses (and never above z = 0, where a free body's goal usually lies),
 * so a model resting at its goal stands on it. `boxAt(poses)` measures the model in MuJoCo's frame.
 */
export function groundHeight(model: ModelView, posesList: Pose[][]): number {
  if (model.floorZ !== null) return model.floorZ;
  let low = 0;
  const saved = model.bodies.map((b) => [b.position.clone(), b.quaternion.clone()] as const);
  const box = new THREE.Box3();
  for (const poses of posesList) {
    model.setPoses(poses);
    model.group.updateMatrixWorld(true);
    // measure in the model group's own frame (MuJoCo's): undo whatever parent transform it has
    const inv = model.group.matrixWorld.clone().invert();
    box.makeEmpty();
    model.group.traverse((o) => {
      if (o instanceof THREE.Mesh) {
        o.geometry.computeBoundingBox();
        const b = o.geometry.boundingBox!.clone().applyMatrix4(o.matrixWorld).applyMatrix4(inv);
        box.union(b);
      }
    });
    if (!box.isEmpty()) low = Math.min(low, box.min.z);
  }
  // back where it was, the skins too
  model.setPoses(saved.map(([p, q]) => [p.x, p.y, p.z, q.w, q.x, q.y, q.z]));
  return low;
}
