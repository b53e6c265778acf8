// A three.js view of MuJoCo models: z is up in `world` (MuJoCo's frame), an orbiting camera, a ground
// grid, and a render every animation frame. Throws WebGLUnavailable when the browser has no WebGL.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { onFrame } from './loop';

export class WebGLUnavailable extends Error {
  constructor() {
    super('This browser cannot draw 3D (WebGL is unavailable or disabled), so the view is empty.');
  }
}

export class Viewer {
  readonly renderer: THREE.WebGLRenderer;
  readonly scene = new THREE.Scene();
  readonly camera = new THREE.PerspectiveCamera(45, 1, 0.05, 2000);
  readonly controls: OrbitControls;
  /** MuJoCo's frame (z up); add models here. */
  readonly world = new THREE.Group();
  readonly grid: THREE.GridHelper;
  private readonly followed = new THREE.Vector3();
  private following: THREE.Vector3 | null = null;
  private readonly beforeRender = new Set<(now: number) => void>();
  private readonly stopLoop: () => void;
  private readonly resize: ResizeObserver;

  constructor(readonly host: HTMLElement) {
    let renderer: THREE.WebGLRenderer;
    try {
      renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    } catch {
      throw new WebGLUnavailable();
    }
    this.renderer = renderer;
    renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    renderer.domElement.className = 'view-canvas';
    host.append(renderer.domElement);
    this.scene.background = new THREE.Color(0x11161d);
    this.world.rotation.x = -Math.PI / 2; // MuJoCo z (up) -> three y (up)
    this.scene.add(this.world);
    this.scene.add(new THREE.HemisphereLight(0xdde6ff, 0x30343a, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(5, 12, 7);
    this.scene.add(sun);
    this.grid = new THREE.GridHelper(400, 200, 0x6b7c8f, 0x3b4755);
    this.grid.rotation.x = Math.PI / 2; // into MuJoCo's xy plane
    this.world.add(this.grid);
    this.controls = new OrbitControls(this.camera, renderer.domElement);
    this.controls.enableDamping = true;
    this.camera.position.set(4, 3, 6);
    this.resize = new ResizeObserver(() => this.fit());
    this.resize.observe(host);
    this.fit();
    this.stopLoop = onFrame((now) => this.render(now));
  }

  /** A point in MuJoCo coordinates -> three's world coordinates. */
  toScene(x: number, y: number, z: number): THREE.Vector3 {
    return new THREE.Vector3(x, y, z).applyMatrix4(this.world.matrixWorld);
  }

  /** Look at `center` (MuJoCo coordinates) from a distance that shows about `radius` around it. */
  frame(center: number[], radius: number): void {
    this.world.updateMatrixWorld();
    const c = this.toScene(center[0] ?? 0, center[1] ?? 0, center[2] ?? 0);
    const r = Math.max(radius, 0.5);
    this.controls.target.copy(c);
    this.camera.position.copy(c).add(new THREE.Vector3(1.0, 1.2, 1.6).normalize().multiplyScalar(r * 3.2));
    this.scene.fog = new THREE.Fog(0x11161d, r * 6, r * 40); // the ground fades out instead of ending
    this.camera.near = r / 100;
    this.camera.far = r * 400;
    this.camera.updateProjectionMatrix();
    this.controls.update();
  }

  /** Keep the camera on a moving point (MuJoCo coordinates); null stops following. */
  follow(point: number[] | null): void {
    if (!point) {
      this.following = null;
      return;
    }
    this.world.updateMatrixWorld();
    const p = this.toScene(point[0] ?? 0, point[1] ?? 0, point[2] ?? 0);
    if (!this.following) {
      // jump to the point at once, keeping the camera's offset; then glide after it
      const jump = p.clone().sub(this.controls.target);
      this.controls.target.add(jump);
      this.camera.position.add(jump);
      this.followed.copy(p);
    }
    this.following = p;
  }

  setGroundHeight(z: number): void {
    this.grid.position.z = z;
  }

  onBeforeRender(f: (now: number) => void): () => void {
    this.beforeRender.add(f);
    return () => this.beforeRender.delete(f);
  }

  private fit(): void {
    const w = Math.max(1, this.host.clientWidth);
    const h = Math.max(1, this.host.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  private render(now: number): void {
    for (const f of this.beforeRender) f(now);
    if (this.following) {
      const delta = this.following.clone().sub(this.followed).multiplyScalar(0.15);
      this.followed.add(delta);
      this.controls.target.add(delta);
      this.camera.position.add(delta);
    }
    this.controls.update();
    this.renderer.render(this.scene, this.camera);
  }

  dispose(): void {
    this.stopLoop();
    this.resize.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
    this.renderer.domElement.remove();
  }
}
