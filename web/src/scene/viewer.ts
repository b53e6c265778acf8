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

/**
 * Whether WebGL is drawn in software (SwiftShader, llvmpipe: no GPU, as in a headless browser or a
 * remote desktop). There every fragment costs CPU, so the views drop multisampling and draw at one
 * device pixel per CSS pixel to keep the display rate.
 */
let software: boolean | undefined;
export function softwareRendering(): boolean {
  if (software === undefined) {
    const gl = document.createElement('canvas').getContext('webgl2') ?? document.createElement('canvas').getContext('webgl');
    const info = gl?.getExtension('WEBGL_debug_renderer_info');
    const name = gl && info ? String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL)) : '';
    software = /swiftshader|llvmpipe|software/i.test(name);
    gl?.getExtension('WEBGL_lose_context')?.loseContext();
  }
  return software;
}

/** A tiled grid texture: one cell per repeat, lines a shade lighter than the ground. */
function gridTexture(repeat: number): THREE.Texture {
  const c = document.createElement('canvas');
  c.width = c.height = 128;
  const g = c.getContext('2d');
  if (g) {
    g.fillStyle = '#1b232c';
    g.fillRect(0, 0, 128, 128);
    g.strokeStyle = '#3d4a58';
    g.lineWidth = 3;
    g.strokeRect(0, 0, 128, 128);
  }
  const t = new THREE.CanvasTexture(c);
  t.wrapS = t.wrapT = THREE.RepeatWrapping;
  t.repeat.set(repeat, repeat);
  t.anisotropy = 4;
  t.colorSpace = THREE.SRGBColorSpace;
  return t;
}

declare global {
  interface Window {
    /** Draws a view's canvas again now, so that its pixels can be read until the task ends (tests). */
    __neuroRedraw?: (canvas: HTMLCanvasElement) => boolean;
  }
}

const viewers = new WeakMap<HTMLCanvasElement, Viewer>();

function redraw(canvas: HTMLCanvasElement): boolean {
  const v = viewers.get(canvas);
  if (!v) return false;
  v.renderer.render(v.scene, v.camera);
  return true;
}

export class Viewer {
  readonly renderer: THREE.WebGLRenderer;
  readonly scene = new THREE.Scene();
  readonly camera = new THREE.PerspectiveCamera(45, 1, 0.05, 2000);
  readonly controls: OrbitControls;
  /** MuJoCo's frame (z up); add models here. */
  readonly world = new THREE.Group();
  private readonly ground: THREE.Mesh;
  private readonly followed = new THREE.Vector3();
  private following: THREE.Vector3 | null = null;
  private lastRender = 0;
  private readonly beforeRender = new Set<(now: number) => void>();
  private readonly stopLoop: () => void;
  private readonly resize: ResizeObserver;

  constructor(readonly host: HTMLElement) {
    let renderer: THREE.WebGLRenderer;
    try {
      // no preserveDrawingBuffer: keeping the buffer costs a full-frame copy every frame; a reader of
      // the pixels calls window.__neuroRedraw(canvas) and reads them in the same task instead
      renderer = new THREE.WebGLRenderer({ antialias: !softwareRendering() });
    } catch {
      throw new WebGLUnavailable();
    }
    this.renderer = renderer;
    renderer.setPixelRatio(softwareRendering() ? 1 : Math.min(window.devicePixelRatio || 1, 2));
    renderer.domElement.className = 'view-canvas';
    host.append(renderer.domElement);
    this.scene.background = new THREE.Color(0x11161d);
    this.world.rotation.x = -Math.PI / 2; // MuJoCo z (up) -> three y (up)
    this.scene.add(this.world);
    this.scene.add(new THREE.HemisphereLight(0xdde6ff, 0x30343a, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(5, 12, 7);
    this.scene.add(sun);
    // the ground: a plane in MuJoCo's xy plane with a 2 m grid drawn into its texture
    this.ground = new THREE.Mesh(
      new THREE.PlaneGeometry(400, 400),
      // Lambert, not the physically based material: a matte ground looks the same and costs far less per pixel
      new THREE.MeshLambertMaterial({ map: gridTexture(200) }),
    );
    this.world.add(this.ground);
    this.controls = new OrbitControls(this.camera, renderer.domElement);
    this.controls.enableDamping = true;
    this.camera.position.set(4, 3, 6);
    this.resize = new ResizeObserver(() => this.fit());
    this.resize.observe(host);
    this.fit();
    this.stopLoop = onFrame((now) => this.render(now));
    viewers.set(renderer.domElement, this);
    window.__neuroRedraw = redraw;
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
    this.ground.position.z = z;
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
    const dt = this.lastRender ? Math.min(1, (now - this.lastRender) / 1000) : 0;
    this.lastRender = now;
    if (this.following) {
      // glide after the point at the same pace whatever the frame rate (15 % per 60 Hz frame)
      const delta = this.following.clone().sub(this.followed).multiplyScalar(1 - Math.pow(0.85, dt * 60));
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
