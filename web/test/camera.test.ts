import * as THREE from 'three';
import { describe, expect, it } from 'vitest';
import { aboveGround, acrossPath, aim, boundingSphere, replayWindow, corners, fitDistance, fitPoints, followPoints, inView, placeCamera, toNdc, viewDirection } from '../src/scene/camera';

const v = (x: number, y: number, z: number): THREE.Vector3 => new THREE.Vector3(x, y, z);

function camera(aspect: number): THREE.PerspectiveCamera {
  return new THREE.PerspectiveCamera(40, aspect, 0.1, 1000);
}

describe('framing', () => {
  it('bounds points in a sphere, ignoring non-finite ones, never smaller than asked', () => {
    const s = boundingSphere([v(-1, 0, 0), v(1, 0, 0), v(NaN, 0, 0)], 0.1);
    expect(s.center.toArray()).toEqual([0, 0, 0]);
    expect(s.radius).toBeCloseTo(1);
    expect(boundingSphere([], 0.5).radius).toBe(0.5);
    expect(boundingSphere([v(2, 2, 2)], 0.5).radius).toBe(0.5);
  });

  it('fits a sphere in the narrower of the two fields of view', () => {
    // a wide view: the vertical field decides; a tall one: the horizontal
    const wide = fitDistance(1, 40, 2, 1);
    expect(wide).toBeCloseTo(1 / Math.sin(THREE.MathUtils.degToRad(20)));
    expect(fitDistance(1, 40, 0.5, 1)).toBeGreaterThan(wide);
    expect(fitDistance(2, 40, 2, 1)).toBeCloseTo(2 * wide);
  });

  it('looks from the azimuth and elevation asked (MuJoCo +x towards +y is three +x towards -z)', () => {
    const d = viewDirection(0, 0);
    expect([d.x, d.y, d.z].map((x) => Math.abs(x) < 1e-12 ? 0 : x)).toEqual([1, 0, 0]);
    expect(viewDirection(90, 0).z).toBeCloseTo(-1);
    expect(viewDirection(0, 90).y).toBeCloseTo(1);
  });

  // the lander-landing task: the lander starts 25 m up and 12 m aside, the goal is on the pad
  it.each([
    ['a wide view', 16 / 9],
    ['a narrow view', 0.8],
  ])('keeps a lander and its far-away goal on screen in %s', (_, aspect) => {
    const lander = new THREE.Box3(v(-10.9, 24.1, -6.9), v(-9.1, 25.8, -5.1));
    const goal = new THREE.Box3(v(-0.9, -0.9, -0.9), v(0.9, 0.8, 0.9));
    const pts = [...corners(lander), ...corners(goal)];
    const cam = camera(aspect);
    placeCamera(cam, boundingSphere(pts), viewDirection(-62, 24));
    for (const p of pts) expect(inView(cam, p)).toBe(true);
    // and both are big enough to see: the lander's box spans more than 2 % of the view's height
    const top = v(-10, 25.8, -6).project(cam);
    const bottom = v(-10, 24.1, -6).project(cam);
    expect(Math.abs(top.y - bottom.y) / 2).toBeGreaterThan(0.02);
  });

  it('frames the ground below a model near it, and the model alone high above it', () => {
    const near = new THREE.Box3(v(-1, 3, -1), v(1, 4, 1));
    expect(followPoints(near, 0, 25)).toHaveLength(9); // the box's corners and the ground below
    expect(followPoints(near, 0, 25)[8]!.toArray()).toEqual([0, 0, 0]);
    const high = new THREE.Box3(v(-1, 300, -1), v(1, 301, 1));
    expect(followPoints(high, 0, 25)).toHaveLength(8);
    expect(followPoints(new THREE.Box3(), 0, 25)).toEqual([]);
    // below the ground (a lander that sank through it): the model alone
    expect(followPoints(new THREE.Box3(v(-1, -9, -1), v(1, -8, 1)), 0, 25)).toHaveLength(8);
  });

  it('does not follow a body down through the ground: it frames the ground above it', () => {
    // the lander 225 m under its pad (a fall the emulator extrapolated): the camera stays on the ground
    const sunk = new THREE.Box3(v(2, -226, -1), v(4, -224, 1));
    const kept = aboveGround(sunk, -0.9);
    expect(kept.min.y).toBeCloseTo(-0.9);
    expect(kept.max.y).toBeCloseTo(1.1);
    expect([kept.min.x, kept.max.x, kept.min.z, kept.max.z]).toEqual([2, 4, -1, 1]);
    const pts = followPoints(kept, -0.9, 30);
    expect(pts).toHaveLength(9); // with the ground below it
    expect(Math.min(...pts.map((p) => p.y))).toBeCloseTo(-0.9);
    const cam = camera(1.6);
    const dir = viewDirection(-62, 15);
    const f = fitPoints(pts, dir, cam.fov, cam.aspect);
    aim(cam, f.target, dir, f.distance);
    expect(cam.position.y).toBeGreaterThan(-0.9); // above the ground, looking at it
    expect(inView(cam, v(3, -0.9, 0))).toBe(true);
    // half through: kept from the ground up; in the air: unchanged
    expect(aboveGround(new THREE.Box3(v(0, -1, 0), v(1, 1, 1)), 0).min.y).toBe(0);
    const air = new THREE.Box3(v(0, 19, 0), v(1, 21, 1));
    expect(aboveGround(air, 0)).toBe(air);
  });

  it('a second framing forgets the first: a pendulum after a lander is centred on the pendulum', () => {
    const cam = camera(1.6);
    placeCamera(cam, boundingSphere(corners(new THREE.Box3(v(-1, 19, -1), v(1, 21, 1)))), viewDirection(-62, 24));
    const pendulum = [...corners(new THREE.Box3(v(-0.3, -1.7, -0.3), v(0.3, 0.1, 0.3))), v(0, -1.72, 0)];
    placeCamera(cam, boundingSphere(pendulum), viewDirection(-62, 24));
    for (const p of pendulum) expect(inView(cam, p)).toBe(true);
    expect(inView(cam, v(0, 20, 0))).toBe(false);
  });
});

describe('fitting points', () => {
  it('sees every point, and fills the view better than a bounding sphere for a long path', () => {
    // the truck-parking path: 20 m ahead and 10 m aside, seen from above and to the side
    const path = [v(0, 0, 0), v(20, 0, -10), v(0, 1, 0), v(20, 1, -10), v(10, 0, -3)];
    const dir = viewDirection(-62, 15);
    const cam = camera(1.6);
    const fit = fitPoints(path, dir, cam.fov, cam.aspect);
    aim(cam, fit.target, dir, fit.distance);
    for (const p of path) expect(inView(cam, p)).toBe(true);
    const xs = path.map((p) => toNdc(cam, p).x);
    expect(Math.max(...xs) - Math.min(...xs)).toBeGreaterThan(1.2); // more than 60 % of the width
    expect(fit.distance).toBeLessThan(placeCamera(camera(1.6), boundingSphere(path), dir));
  });

  it('ignores non-finite points and has a sane distance for a single point', () => {
    const f = fitPoints([v(1, 2, 3), v(NaN, 0, 0)], viewDirection(0, 30), 40, 1);
    expect(f.target.toArray()).toEqual([1, 2, 3]);
    expect(f.distance).toBeGreaterThan(0);
    expect(fitPoints([], viewDirection(0, 30), 40, 1).distance).toBe(1);
  });
});

describe('replay framing', () => {
  const m = (x: number, y: number, z: number) => new THREE.Vector3(x, y, z);
  const angle = (a: number, b: number) => Math.abs(((a - b + 540) % 360) - 180);

  it('looks across a path, never along it', () => {
    // the truck drives along +x, then turns 90° to +y: seen from above, across the diagonal of the turn
    const truck = [...Array.from({ length: 10 }, (_, i) => m(i, 0, 0.5)), ...Array.from({ length: 10 }, (_, i) => m(10, i, 0.5))];
    const t = acrossPath(truck);
    expect(t.elevation).toBeGreaterThanOrEqual(45);
    // not along the turn's main direction, from its start (0, 0) towards its end (10, 9): about 42°
    expect(angle(t.azimuth, 42)).toBeGreaterThan(80);
    expect(angle(t.azimuth, -138)).toBeGreaterThan(80);
    // a straight path along x is seen from the side (azimuth ±90°)
    const straight = acrossPath(Array.from({ length: 10 }, (_, i) => m(i * 3, 0, 0)));
    expect(angle(straight.azimuth, -90)).toBeLessThan(1);
    // the lander's descent: 25 m down while drifting 12 m along x: from the side, low, its drift across
    const lander = acrossPath(Array.from({ length: 20 }, (_, i) => m(12 - 12 * (i / 19) ** 2, 0.2 * i, 25 - 25 * (i / 19))));
    expect(lander.elevation).toBeLessThan(20);
    expect(Math.abs(Math.cos(THREE.MathUtils.degToRad(lander.azimuth)))).toBeLessThan(0.3);
  });

  it('keeps a body on a long path a fair share of the view, sliding the window towards the goal', () => {
    const region = new THREE.Box3(m(-1, -1, -1), m(13, 25, 1)); // three's frame: y up, 26 m tall
    const body = new THREE.Box3(m(11, 23, -0.9), m(12.9, 24.6, 0.9));
    const w = replayWindow(body, region, 12);
    expect(w.max.y - w.min.y).toBeCloseTo(12);
    expect(w.max.y).toBeCloseTo(25); // slid inside the region, the body in it
    expect(w.containsBox(body)).toBe(true);
    expect(w.max.x - w.min.x).toBeCloseTo(12);
    expect(w.max.z - w.min.z).toBeCloseTo(2); // the region where it is smaller than the window
    const landed = replayWindow(new THREE.Box3(m(-0.9, -0.9, -0.9), m(0.9, 0.7, 0.9)), region, 12);
    expect(landed.min.y).toBeCloseTo(-1); // at the end the window reaches the goal on the ground
    // a short path (the truck's) is framed whole
    const small = new THREE.Box3(m(0, 0, 0), m(8, 2, 8));
    expect(replayWindow(new THREE.Box3(m(1, 0, 1), m(3, 1.5, 2)), small, 20)).toEqual(small);
  });
});
