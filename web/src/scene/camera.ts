// Framing: where a perspective camera must stand to show a set of points (a model at its poses, its
// goal, the ground below it) whole. Pure three.js math (no WebGL), so it is unit-tested in Node.
//
// Coordinates here are three's world frame (y up): the viewer turns MuJoCo's z-up frame into it.
import * as THREE from 'three';

export interface Sphere {
  center: THREE.Vector3;
  radius: number;
}

/** The smallest axis-aligned box's bounding sphere of `points`, at least `minRadius` wide. */
export function boundingSphere(points: THREE.Vector3[], minRadius = 0.5): Sphere {
  const box = new THREE.Box3();
  for (const p of points) if (Number.isFinite(p.x) && Number.isFinite(p.y) && Number.isFinite(p.z)) box.expandByPoint(p);
  if (box.isEmpty()) return { center: new THREE.Vector3(), radius: minRadius };
  const s = box.getBoundingSphere(new THREE.Sphere());
  return { center: s.center, radius: Math.max(s.radius, minRadius) };
}

/**
 * The distance from a sphere's centre at which the whole sphere fits a perspective camera with
 * vertical field of view `fovDeg` and `aspect` (width / height), with `margin` (1.2: 20 % around).
 */
export function fitDistance(radius: number, fovDeg: number, aspect: number, margin = 1.2): number {
  const vHalf = THREE.MathUtils.degToRad(fovDeg) / 2;
  const hHalf = Math.atan(Math.tan(vHalf) * Math.max(aspect, 1e-3));
  const half = Math.min(vHalf, hHalf);
  return (radius * margin) / Math.sin(half);
}

/** A unit direction from the target towards the camera: `azimuthDeg` about the vertical (y), measured
 * from +x towards -z (MuJoCo's +x towards +y), and `elevationDeg` above the horizon. */
export function viewDirection(azimuthDeg: number, elevationDeg: number): THREE.Vector3 {
  const az = THREE.MathUtils.degToRad(azimuthDeg);
  const el = THREE.MathUtils.degToRad(elevationDeg);
  return new THREE.Vector3(Math.cos(el) * Math.cos(az), Math.sin(el), -Math.cos(el) * Math.sin(az));
}

/** Place `camera` looking at `sphere` from `direction` (unit, target → camera) so that it fits. */
export function placeCamera(camera: THREE.PerspectiveCamera, sphere: Sphere, direction: THREE.Vector3, margin = 1.2): number {
  const d = fitDistance(sphere.radius, camera.fov, camera.aspect, margin);
  aim(camera, sphere.center, direction, d);
  return d;
}

/**
 * Where to stand to see every one of `points` from `direction` (unit, target → camera), as close as
 * possible: the target is the middle of their box, and the distance the least at which each point is
 * inside the view with `margin` around (1.15: 15 %). Tighter than fitting their bounding sphere when
 * they spread along a line or a plane (a path, a model and its distant goal).
 */
export function fitPoints(points: THREE.Vector3[], direction: THREE.Vector3, fovDeg: number, aspect: number, margin = 1.15): { target: THREE.Vector3; distance: number } {
  const box = new THREE.Box3().setFromPoints(points.filter((p) => Number.isFinite(p.x + p.y + p.z)));
  if (box.isEmpty()) return { target: new THREE.Vector3(), distance: 1 };
  const target = box.getCenter(new THREE.Vector3());
  const back = direction.clone().normalize();
  // the camera's right and up vectors when it looks along -back with y up
  const right = new THREE.Vector3(0, 1, 0).cross(back);
  if (right.lengthSq() < 1e-9) right.set(1, 0, 0);
  right.normalize();
  const up = back.clone().cross(right).normalize();
  const tanV = Math.tan(THREE.MathUtils.degToRad(fovDeg) / 2);
  const tanH = tanV * Math.max(aspect, 1e-3);
  let distance = 0;
  for (const p of points) {
    if (!Number.isFinite(p.x + p.y + p.z)) continue;
    const r = p.clone().sub(target);
    const along = r.dot(back); // towards the camera
    distance = Math.max(distance, along + (Math.abs(r.dot(right)) * margin) / tanH, along + (Math.abs(r.dot(up)) * margin) / tanV);
  }
  const size = box.getSize(new THREE.Vector3()).length();
  return { target, distance: Math.max(distance, size * 0.05, 0.5) };
}

/** Point `camera` at `target` from `distance` along `direction`, with depth limits to match. */
export function aim(camera: THREE.PerspectiveCamera, target: THREE.Vector3, direction: THREE.Vector3, distance: number): void {
  camera.position.copy(target).addScaledVector(direction.clone().normalize(), distance);
  camera.near = Math.max(distance / 200, 0.01);
  camera.far = Math.max(distance * 60, 500);
  camera.lookAt(target);
  camera.updateProjectionMatrix();
  camera.updateMatrixWorld();
}

/** Normalised device coordinates of a point seen by `camera` (inside the view: both in [-1, 1], z < 1). */
export function toNdc(camera: THREE.Camera, p: THREE.Vector3): THREE.Vector3 {
  camera.updateMatrixWorld();
  return p.clone().project(camera);
}

export function inView(camera: THREE.Camera, p: THREE.Vector3): boolean {
  const n = toNdc(camera, p);
  return Math.abs(n.x) <= 1 && Math.abs(n.y) <= 1 && n.z < 1;
}

/**
 * What the following camera frames: the model's box, and the ground below it while the model is
 * within `groundReach` of the ground (so up and down stay readable and the shadow is seen); higher
 * up, the model alone (the sky and the horizon still say which way is up).
 */
export function followPoints(model: THREE.Box3, groundY: number, groundReach: number): THREE.Vector3[] {
  if (model.isEmpty()) return [];
  const pts = corners(model);
  const height = model.min.y - groundY;
  if (height >= -1e-6 && height <= groundReach) {
    const c = model.getCenter(new THREE.Vector3());
    pts.push(new THREE.Vector3(c.x, groundY, c.z));
  }
  return pts;
}

/**
 * A followed box kept on or above the ground (y >= groundY): a body that went through the ground (an
 * emulator extrapolating a fall far outside what it learnt) is not followed down there, where there is
 * nothing but fog to see, but shown as the spot on the ground above it, its size kept, with the ground
 * and what stands on it in view.
 */
export function aboveGround(box: THREE.Box3, groundY: number): THREE.Box3 {
  if (box.isEmpty() || box.min.y >= groundY) return box;
  const out = box.clone();
  const height = box.max.y - box.min.y;
  out.min.y = groundY;
  out.max.y = Math.max(box.max.y, groundY + Math.min(height, 5));
  return out;
}

/** The eight corners of a box. */
export function corners(box: THREE.Box3): THREE.Vector3[] {
  if (box.isEmpty()) return [];
  const out: THREE.Vector3[] = [];
  for (const x of [box.min.x, box.max.x]) for (const y of [box.min.y, box.max.y]) for (const z of [box.min.z, box.max.z]) out.push(new THREE.Vector3(x, y, z));
  return out;
}

/**
 * Where to look at a path from (`path`: points in MuJoCo's frame, z up): across its main direction,
 * never along it. A path that is mostly vertical (the lander's descent) is seen from the side, low, with
 * its sideways drift across the view; a path on the ground (the truck's parking turn) from above at an
 * angle, across its main direction, so a turn is not foreshortened. Of the two sides, the one nearer
 * `preferredAzimuth` (the usual view); that azimuth alone for a path that barely moves sideways.
 */
export function acrossPath(path: THREE.Vector3[], preferredAzimuth = -62): { azimuth: number; elevation: number } {
  const pts = path.filter((p) => Number.isFinite(p.x + p.y + p.z));
  if (pts.length < 2) return { azimuth: preferredAzimuth, elevation: 15 };
  const n = pts.length;
  const mx = pts.reduce((s, p) => s + p.x, 0) / n;
  const my = pts.reduce((s, p) => s + p.y, 0) / n;
  let sxx = 0;
  let syy = 0;
  let sxy = 0;
  for (const p of pts) {
    sxx += (p.x - mx) ** 2;
    syy += (p.y - my) ** 2;
    sxy += (p.x - mx) * (p.y - my);
  }
  const zs = pts.map((p) => p.z);
  const vertical = Math.max(...zs) - Math.min(...zs);
  // the spread along the main horizontal direction (the larger eigenvalue's root, as a range)
  const spread = 2 * Math.sqrt((sxx + syy) / 2 / n + Math.sqrt(((sxx - syy) / 2 / n) ** 2 + (sxy / n) ** 2));
  const elevation = vertical > spread ? 12 : 50;
  if (spread < 1e-3) return { azimuth: preferredAzimuth, elevation };
  const main = THREE.MathUtils.radToDeg(0.5 * Math.atan2(2 * sxy, sxx - syy)); // the main direction, degrees from +x
  const gap = (a: number): number => Math.abs(((a - preferredAzimuth + 540) % 360) - 180);
  const azimuth = [main + 90, main - 90].sort((a, b) => gap(a) - gap(b))[0]!;
  return { azimuth: ((azimuth + 540) % 360) - 180, elevation };
}

/**
 * What a replay's camera keeps framed while the body moves: the whole region (the path, its goal,
 * the body at both ends) when it is no more than `size` across on an axis, and on an axis where it is
 * larger a window `size` wide around the body, slid to stay inside the region. A body on a long path (the
 * lander 25 m above its pad) is then a sixth of the view, not a few pixels, and the view still ends on
 * the goal. Boxes in three's frame.
 */
export function replayWindow(body: THREE.Box3, region: THREE.Box3, size: number): THREE.Box3 {
  if (body.isEmpty()) return region.clone();
  if (region.isEmpty()) return body.clone();
  const c = body.getCenter(new THREE.Vector3());
  const out = new THREE.Box3();
  for (const axis of ['x', 'y', 'z'] as const) {
    const lo = region.min[axis];
    const hi = region.max[axis];
    if (hi - lo <= size) {
      out.min[axis] = lo;
      out.max[axis] = hi;
    } else {
      const mid = THREE.MathUtils.clamp(c[axis], lo + size / 2, hi - size / 2);
      out.min[axis] = mid - size / 2;
      out.max[axis] = mid + size / 2;
    }
  }
  return out.union(body);
}
