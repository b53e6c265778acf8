// A model drawn from its MJCF geometry (GET /models/{model}/geometry): one group per body, placed by
// world poses [x, y, z, qw, qx, qy, qz]; geoms are boxes, spheres, capsules, cylinders, ellipsoids and
// planes in their body's frame. A "ghost" is the same model translucent (the MuJoCo twin, a target).
import * as THREE from 'three';
import type { GeomInfo, ModelGeometry } from '../api/emulator.gen';
import type { Pose } from './interp';

export interface Look {
  ghost?: boolean;
  color?: number; // overrides the MJCF colours (ghosts and targets)
  opacity?: number;
}

function shape(g: GeomInfo): THREE.BufferGeometry | null {
  const [a = 0.05, b = 0.05, c = 0.05] = g.size;
  switch (g.type) {
    case 'box':
    case 'mesh':
      return new THREE.BoxGeometry(2 * a, 2 * b, 2 * c);
    case 'sphere':
      return new THREE.SphereGeometry(a, 24, 16);
    case 'ellipsoid':
      return new THREE.SphereGeometry(1, 24, 16).scale(a, b, c);
    case 'capsule': // three's capsule and cylinder run along y; MuJoCo's along the geom's z
      return new THREE.CapsuleGeometry(a, 2 * b, 8, 16).rotateX(Math.PI / 2);
    case 'cylinder':
      return new THREE.CylinderGeometry(a, a, 2 * b, 24).rotateX(Math.PI / 2);
    case 'plane':
      return new THREE.PlaneGeometry(a > 0 ? 2 * a : 200, b > 0 ? 2 * b : 200);
    default:
      return null;
  }
}

function material(g: GeomInfo, look: Look): THREE.Material {
  const [r = 0.7, gr = 0.7, b = 0.7, a = 1] = g.rgba;
  const color = look.color !== undefined ? new THREE.Color(look.color) : new THREE.Color(r, gr, b);
  const opacity = look.ghost ? (look.opacity ?? 0.35) : a;
  return new THREE.MeshStandardMaterial({
    color,
    roughness: 0.55,
    metalness: 0.1,
    transparent: opacity < 1,
    opacity,
    depthWrite: opacity >= 1,
    side: g.type === 'plane' ? THREE.DoubleSide : THREE.FrontSide,
  });
}

function setPose(o: THREE.Object3D, p: number[]): void {
  o.position.set(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0);
  o.quaternion.set(p[4] ?? 0, p[5] ?? 0, p[6] ?? 0, p[3] ?? 1); // [w,x,y,z] -> three's (x,y,z,w)
}

export class ModelView {
  readonly group = new THREE.Group();
  readonly bodies: THREE.Group[];

  constructor(
    readonly geometry: ModelGeometry,
    look: Look = {},
  ) {
    this.bodies = geometry.bodies.map((body) => {
      const g = new THREE.Group();
      g.name = body.name;
      for (const geom of body.geoms) {
        const mesh = this.mesh(geom, look);
        if (mesh) g.add(mesh);
      }
      this.group.add(g);
      return g;
    });
    if (!look.ghost) {
      for (const geom of geometry.world) {
        const mesh = this.mesh(geom, look);
        if (mesh) this.group.add(mesh);
      }
    }
    this.setPoses(geometry.rest_poses);
  }

  private mesh(geom: GeomInfo, look: Look): THREE.Mesh | null {
    if (geom.group !== undefined && geom.group >= 3) return null; // MuJoCo hides groups 3-5 by default
    const s = shape(geom);
    if (!s) return null;
    const mesh = new THREE.Mesh(s, material(geom, look));
    mesh.name = geom.name;
    setPose(mesh, [...geom.pos, ...geom.quat]);
    if (look.ghost) mesh.renderOrder = 1;
    return mesh;
  }

  setPoses(poses: Pose[]): void {
    poses.forEach((p, i) => {
      const b = this.bodies[i];
      if (b) setPose(b, p);
    });
  }

  set visible(v: boolean) {
    this.group.visible = v;
  }

  dispose(): void {
    this.group.traverse((o) => {
      if (o instanceof THREE.Mesh) {
        o.geometry.dispose();
        (o.material as THREE.Material).dispose();
      }
    });
    this.group.removeFromParent();
  }
}
