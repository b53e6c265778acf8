// The path a body has taken: a line through its last positions (MuJoCo's frame), fading with age.
import * as THREE from 'three';

export class Trail {
  readonly line: THREE.Line;
  private readonly positions: Float32Array;
  private readonly colors: Float32Array;
  private readonly color: THREE.Color;
  private count = 0;
  private readonly last = new THREE.Vector3(NaN, NaN, NaN);

  constructor(
    color: number,
    private readonly capacity = 1200,
    private readonly minStep = 0.02, // metres between kept points
  ) {
    this.color = new THREE.Color(color);
    this.positions = new Float32Array(capacity * 3);
    this.colors = new Float32Array(capacity * 3);
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(this.positions, 3).setUsage(THREE.DynamicDrawUsage));
    g.setAttribute('color', new THREE.BufferAttribute(this.colors, 3).setUsage(THREE.DynamicDrawUsage));
    g.setDrawRange(0, 0);
    this.line = new THREE.Line(g, new THREE.LineBasicMaterial({ vertexColors: true, transparent: true, opacity: 0.9 }));
    this.line.frustumCulled = false;
    this.line.name = 'trail';
  }

  get size(): number {
    return this.count;
  }

  clear(): void {
    this.count = 0;
    this.last.set(NaN, NaN, NaN);
    this.line.geometry.setDrawRange(0, 0);
  }

  /** Add a position; points closer than `minStep` to the last kept one are skipped. */
  push(x: number, y: number, z: number): void {
    if (![x, y, z].every(Number.isFinite)) return;
    if (this.count && this.last.distanceTo(new THREE.Vector3(x, y, z)) < this.minStep) return;
    this.last.set(x, y, z);
    if (this.count === this.capacity) {
      this.positions.copyWithin(0, 3);
      this.count -= 1;
    }
    this.positions.set([x, y, z], this.count * 3);
    this.count += 1;
    this.recolor();
  }

  /** Replace the whole path (a replay's trajectory). */
  set(points: number[][]): void {
    this.clear();
    for (const p of points) this.push(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0);
  }

  private recolor(): void {
    const n = this.count;
    const bg = new THREE.Color(0x222a33);
    const c = new THREE.Color();
    for (let i = 0; i < n; i++) {
      // old points fade towards the ground's colour, the newest is the trail's full colour
      c.copy(bg).lerp(this.color, 0.25 + 0.75 * ((i + 1) / n));
      this.colors.set([c.r, c.g, c.b], i * 3);
    }
    const g = this.line.geometry;
    g.setDrawRange(0, n);
    (g.getAttribute('position') as THREE.BufferAttribute).needsUpdate = true;
    (g.getAttribute('color') as THREE.BufferAttribute).needsUpdate = true;
  }

  dispose(): void {
    this.line.geometry.dispose();
    (this.line.material as THREE.Material).dispose();
    this.line.removeFromParent();
  }
}

/** A thin vertical line from a point down to the ground, with a ring where it meets it: where a
 * flying body is above the ground, and how high. */
export class DropLine {
  readonly group = new THREE.Group();
  private readonly line: THREE.Line;
  private readonly ring: THREE.Mesh;

  constructor(color: number, ringRadius = 0.6) {
    const g = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 0, -1)]);
    this.line = new THREE.Line(g, new THREE.LineDashedMaterial({ color, dashSize: 0.4, gapSize: 0.3, transparent: true, opacity: 0.8 }));
    this.line.computeLineDistances();
    this.ring = new THREE.Mesh(
      new THREE.RingGeometry(ringRadius * 0.8, ringRadius, 40),
      new THREE.MeshBasicMaterial({ color, transparent: true, opacity: 0.85, side: THREE.DoubleSide, depthWrite: false }),
    );
    this.ring.renderOrder = 1;
    this.group.add(this.line, this.ring);
    this.group.name = 'drop-line';
  }

  /** From (x, y, z) down to the ground at height `ground` (MuJoCo's frame). */
  set(x: number, y: number, z: number, ground: number): void {
    const h = z - ground;
    this.group.visible = Number.isFinite(h);
    if (!this.group.visible) return;
    this.group.position.set(x, y, ground + 0.01);
    const len = Math.max(h - 0.01, 1e-3);
    this.line.scale.set(1, 1, len);
    this.line.position.z = len;
    (this.line.material as THREE.LineDashedMaterial).scale = len; // dashes of the same length at any height
    this.line.visible = h > 0.3;
  }

  dispose(): void {
    this.line.geometry.dispose();
    (this.line.material as THREE.Material).dispose();
    this.ring.geometry.dispose();
    (this.ring.material as THREE.Material).dispose();
    this.group.removeFromParent();
  }
}
