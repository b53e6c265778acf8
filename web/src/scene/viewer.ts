// A three.js view of MuJoCo models: z is up in `world` (MuJoCo's frame); a sky with a horizon, a sun
// that casts shadows onto a gridded ground, an orbiting camera that frames what it is given (a model
// and its goal; a moving model and the ground below it), and a render every animation frame while
// something moves. Throws WebGLUnavailable when the browser has no WebGL.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { aboveGround, corners, fitPoints, followPoints, viewDirection } from './camera';
import { onFrame, resolutionScale } from './loop';

export class WebGLUnavailable extends Error {
  constructor() {
    super('This browser cannot draw 3D (WebGL is unavailable or disabled), so the view is empty.');
  }
}

/**
 * Whether WebGL is drawn in software (SwiftShader, llvmpipe: no GPU, as in a headless browser or a
 * remote desktop). There every fragment costs CPU, so the views drop multisampling, draw at one
 * device pixel per CSS pixel, draw contact shadows instead of shadow maps, a coarser sky, rounded
 * shapes of fewer facets, and a ground whose grid is worked out per pixel instead of sampled from a
 * texture.
 */
let software: boolean | undefined;
export function softwareRendering(): boolean {
  if (software === undefined) {
    if (typeof document === 'undefined') return false; // no page (a unit test): nothing is drawn
    const gl = document.createElement('canvas').getContext('webgl2') ?? document.createElement('canvas').getContext('webgl');
    const info = gl?.getExtension('WEBGL_debug_renderer_info');
    const name = gl && info ? String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL)) : '';
    software = /swiftshader|llvmpipe|software/i.test(name);
    gl?.getExtension('WEBGL_lose_context')?.loseContext();
  }
  return software;
}

export const SKY = { top: 0x1b3354, horizon: 0x8fa6bd, below: 0x2a2f36 };
const GROUND = '#5b6168';
const GROUND_LINE = '#737a82';

/** A tiled grid texture: five 1 m cells per repeat, every fifth line stronger; anisotropic filtering
 * keeps far lines crisp. */
function gridTexture(): THREE.Texture {
  const c = document.createElement('canvas');
  c.width = c.height = 256;
  const g = c.getContext('2d');
  if (g) {
    g.fillStyle = GROUND;
    g.fillRect(0, 0, 256, 256);
    g.strokeStyle = GROUND_LINE;
    g.lineWidth = 2;
    for (let i = 0; i <= 5; i++) {
      const p = (i * 256) / 5;
      g.lineWidth = i === 0 || i === 5 ? 4 : 1.5;
      g.beginPath();
      g.moveTo(p, 0);
      g.lineTo(p, 256);
      g.moveTo(0, p);
      g.lineTo(256, p);
      g.stroke();
    }
  }
  const t = new THREE.CanvasTexture(c);
  t.wrapS = t.wrapT = THREE.RepeatWrapping;
  t.anisotropy = 8;
  t.colorSpace = THREE.SRGBColorSpace;
  return t;
}

/** The ground with a GPU: the grid as a texture on a matte (Lambert) surface that receives the sun's
 * shadows; `extent` is the plane's side in metres. */
function texturedGround(extent: number): THREE.MeshLambertMaterial {
  const tex = gridTexture();
  tex.repeat.set(extent / 5, extent / 5);
  return new THREE.MeshLambertMaterial({ map: tex, side: THREE.DoubleSide });
}

/** What a matte ground facing up reflects of the lights, per unit of albedo (linear colour): three's
 * Lambert shading, the sky half of the hemisphere light and the sun at its angle, over π. */
function groundLight(hemisphere: THREE.HemisphereLight, sun: THREE.DirectionalLight, sunDir: THREE.Vector3): THREE.Color {
  const up = Math.max(0, sunDir.y);
  return hemisphere.color
    .clone()
    .multiplyScalar(hemisphere.intensity)
    .add(sun.color.clone().multiplyScalar(sun.intensity * up))
    .multiplyScalar(1 / Math.PI);
}

/**
 * The ground for software WebGL: the same grid as `gridTexture`, worked out per pixel from the position
 * on the plane, with the light a flat ground receives folded into its two colours. A textured, lit
 * ground costs a filtered texture lookup and the lighting per pixel, which on the CPU was a sixth of a
 * frame; this is a few multiplications. Lines thinner than a pixel fade to their share of it, as a
 * mipmapped texture's do. `lit` is the irradiance on the ground over π (linear colour).
 */
function gridGroundMaterial(lit: THREE.Color): THREE.ShaderMaterial {
  const colour = (hex: string) => new THREE.Color(hex).multiply(lit);
  return new THREE.ShaderMaterial({
    uniforms: THREE.UniformsUtils.merge([
      THREE.UniformsLib.fog,
      { base: { value: colour(GROUND) }, line: { value: colour(GROUND_LINE) } },
    ]),
    vertexShader: `varying vec2 vGrid;
      #include <fog_pars_vertex>
      void main() {
        vGrid = position.xy; // metres on the plane (MuJoCo's x and y)
        vec4 mvPosition = modelViewMatrix * vec4(position, 1.0);
        gl_Position = projectionMatrix * mvPosition;
        #include <fog_vertex>
      }`,
    fragmentShader: `uniform vec3 base; uniform vec3 line; varying vec2 vGrid;
      #include <fog_pars_fragment>
      // coverage of a pixel by lines \`width\` metres wide every \`spacing\` metres
      float lines(float width, float spacing) {
        vec2 w = fwidth(vGrid);
        vec2 d = abs(fract(vGrid / spacing - 0.5) - 0.5) * spacing;
        vec2 k = clamp((0.5 * (width + w) - d) / w, 0.0, 1.0) * min(vec2(1.0), width / w);
        // where a pixel spans a whole cell, the average share of the cell the lines cover
        vec2 far = clamp(w / spacing - 0.5, 0.0, 1.0);
        k = mix(k, vec2(width / spacing), far);
        return max(k.x, k.y);
      }
      void main() {
        gl_FragColor = vec4(mix(base, line, max(lines(0.03, 1.0), lines(0.08, 5.0))), 1.0);
        #include <tonemapping_fragment>
        #include <colorspace_fragment>
        #include <fog_fragment>
      }`,
    side: THREE.DoubleSide,
    fog: true,
  });
}

/**
 * A sky dome: a gradient from the zenith to the horizon, darker below it, following the camera. The
 * colour is worked out per vertex (the fragment shader only passes it on), and the dome is drawn after
 * the opaque scene at the far plane with the depth test on, so only the pixels where the sky shows are
 * shaded (in software WebGL a full-screen pass costs as much as the rest of the frame).
 */
function skyDome(soft: boolean): THREE.Mesh {
  const material = new THREE.ShaderMaterial({
    uniforms: {
      top: { value: new THREE.Color(SKY.top) },
      horizon: { value: new THREE.Color(SKY.horizon) },
      below: { value: new THREE.Color(SKY.below) },
    },
    vertexShader: `uniform vec3 top; uniform vec3 horizon; uniform vec3 below; varying vec3 vColor;
      void main() {
        float h = normalize(position).y;
        vColor = h > 0.0 ? mix(horizon, top, pow(min(h * 1.6, 1.0), 0.7)) : mix(horizon, below, min(-h * 6.0, 1.0));
        gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
        gl_Position.z = gl_Position.w; // at the far plane: behind everything
      }`,
    fragmentShader: `varying vec3 vColor;
      void main() {
        gl_FragColor = vec4(vColor, 1.0);
        #include <colorspace_fragment>
      }`,
    side: THREE.BackSide,
    depthWrite: false,
    depthTest: true,
    depthFunc: THREE.LessEqualDepth,
    fog: false,
  });
  // rows close to the horizon, where the gradient changes fastest
  // software WebGL pays for every vertex of the dome each frame; a coarser one looks nearly the same
  const dome = new THREE.Mesh(soft ? new THREE.SphereGeometry(1, 12, 16) : new THREE.SphereGeometry(1, 32, 48), material);
  dome.renderOrder = 10; // after the opaque scene (the ground, the models), before anything transparent
  dome.frustumCulled = false;
  return dome;
}

/** A soft dark disc, the texture of a contact shadow. */
function blobTexture(): THREE.Texture {
  const c = document.createElement('canvas');
  c.width = c.height = 64;
  const g = c.getContext('2d');
  if (g) {
    const r = g.createRadialGradient(32, 32, 0, 32, 32, 32);
    r.addColorStop(0, 'rgba(0,0,0,1)');
    r.addColorStop(0.5, 'rgba(0,0,0,0.6)');
    r.addColorStop(1, 'rgba(0,0,0,0)');
    g.fillStyle = r;
    g.fillRect(0, 0, 64, 64);
  }
  return new THREE.CanvasTexture(c);
}

/**
 * Contact shadows for software WebGL: one soft disc on the ground below each object of the world that
 * casts a shadow, wider and fainter as it rises. A shadow map costs a second pass over every caster
 * and a filtered lookup per ground pixel, which on the CPU is most of a frame; a disc is a few hundred
 * blended pixels and still shows how high a body is and where it will land.
 */
class BlobShadows {
  readonly group = new THREE.Group();
  private readonly texture = blobTexture();
  private readonly discs: THREE.Mesh[] = [];
  private readonly box = new THREE.Box3();
  private readonly part = new THREE.Box3();

  /** Places a disc below each child of `world` with shadow-casting meshes (three's world frame, y up),
   * and one apart below each part of it marked `userData.shadowApart` (what a model has fixed to the
   * world: the lander's pad stays at the origin while the lander flies 20 m away, and one disc under
   * both would darken the ground between them). */
  update(world: THREE.Object3D, groundY: number): void {
    let used = 0;
    const casters = world.children.filter((c) => c.visible);
    for (let k = 0; k < casters.length; k++) {
      const child = casters[k]!;
      this.box.makeEmpty();
      this.casting(child, child, casters);
      if (this.box.isEmpty()) continue;
      const width = Math.max(this.box.max.x - this.box.min.x, this.box.max.z - this.box.min.z);
      const height = Math.max(0, this.box.min.y - groundY);
      const disc = this.disc(used++);
      const grow = 1 + (0.5 * height) / (width + 0.5);
      disc.position.set((this.box.min.x + this.box.max.x) / 2, groundY + 0.004 * (1 + width), (this.box.min.z + this.box.max.z) / 2);
      disc.scale.setScalar(width * 0.75 * grow);
      (disc.material as THREE.MeshBasicMaterial).opacity = 0.55 / (grow * grow);
      disc.visible = true;
    }
    for (let i = used; i < this.discs.length; i++) this.discs[i]!.visible = false;
  }

  /** Adds the visible shadow-casting meshes under `o` to the box; a part marked `shadowApart` (other
   * than `root`) goes to `later`, for a disc of its own. */
  private casting(o: THREE.Object3D, root: THREE.Object3D, later: THREE.Object3D[]): void {
    if (!o.visible) return;
    if (o !== root && o.userData.shadowApart) {
      later.push(o);
      return;
    }
    if ((o as THREE.Mesh).isMesh && o.castShadow) this.box.union(this.part.setFromObject(o, false));
    for (const c of o.children) this.casting(c, root, later);
  }

  private disc(i: number): THREE.Mesh {
    let d = this.discs[i];
    if (!d) {
      const m = new THREE.MeshBasicMaterial({ map: this.texture, transparent: true, depthWrite: false, fog: false });
      d = new THREE.Mesh(new THREE.PlaneGeometry(2, 2), m);
      d.rotation.x = -Math.PI / 2;
      d.renderOrder = 1;
      this.discs.push(d);
      this.group.add(d);
    }
    return d;
  }
}

declare global {
  interface Window {
    /** Draws a view's canvas again now, so that its pixels can be read until the task ends, and writes its
     * marks (data-screen-*) for that picture (tests). */
    __neuroRedraw?: (canvas: HTMLCanvasElement) => boolean;
  }
}

const viewers = new WeakMap<HTMLCanvasElement, Viewer>();

function redraw(canvas: HTMLCanvasElement): boolean {
  const v = viewers.get(canvas);
  if (!v) return false;
  v.drawNow();
  return true;
}

/** What the camera does: stay (the person orbits), or keep a moving object framed. */
interface Follow {
  box: () => THREE.Box3 | null; // the object's box in three's world frame, each frame
  zoom: number; // the person's zoom relative to the automatic distance
  groundReach: number | null; // how near the ground the box must be to frame the ground too (null: the usual)
  margin: number; // room framed around the box's middle, in its sizes (0.5: half its diagonal each way)
}

export class Viewer {
  readonly renderer: THREE.WebGLRenderer;
  readonly scene = new THREE.Scene();
  readonly camera = new THREE.PerspectiveCamera(40, 1, 0.05, 2000);
  readonly controls: OrbitControls;
  /** MuJoCo's frame (z up); add models here. */
  readonly world = new THREE.Group();
  /** The ground's height in MuJoCo's frame. */
  groundZ = 0;
  /** Draw every frame (a live session, a replay), not only when something changed. */
  animating = false;
  private readonly ground: THREE.Mesh;
  private readonly sky: THREE.Mesh;
  private blobs: BlobShadows | null = null;
  private readonly sun: THREE.DirectionalLight;
  private readonly sunDir = new THREE.Vector3(0.45, 1, 0.3).normalize();
  private following: Follow | null = null;
  private readonly followed = new THREE.Vector3(NaN, NaN, NaN); // the followed box's centre last frame
  private dirty = true;
  private visible = true;
  private userBusy = false;
  private scale = 0;
  private lastRender = 0;
  private readonly basePixelRatio: number;
  private readonly beforeRender = new Set<(now: number) => void>();
  private readonly marks = new Map<string, () => THREE.Object3D | null>();
  private lastMarks = 0;
  private framing = ''; // what the following camera frames, in words (data-framing on the host)
  private readonly stopLoop: () => void;
  private readonly resize: ResizeObserver;
  private readonly seen: IntersectionObserver;

  constructor(readonly host: HTMLElement) {
    let renderer: THREE.WebGLRenderer;
    const soft = softwareRendering();
    try {
      // no preserveDrawingBuffer: keeping the buffer costs a full-frame copy every frame; a reader of
      // the pixels calls window.__neuroRedraw(canvas) and reads them in the same task instead
      renderer = new THREE.WebGLRenderer({ antialias: !soft, powerPreference: 'high-performance' });
    } catch {
      throw new WebGLUnavailable();
    }
    this.renderer = renderer;
    this.basePixelRatio = soft ? 1 : Math.min(window.devicePixelRatio || 1, 2);
    // with a GPU the sun casts shadow maps; in software, contact shadows (BlobShadows) stand in for them
    renderer.shadowMap.enabled = !soft;
    renderer.shadowMap.type = THREE.PCFSoftShadowMap;
    renderer.toneMapping = THREE.ACESFilmicToneMapping;
    renderer.toneMappingExposure = 1.05;
    renderer.domElement.className = 'view-canvas';
    host.append(renderer.domElement);

    this.sky = skyDome(soft);
    this.scene.add(this.sky);
    this.scene.fog = new THREE.Fog(SKY.horizon, 60, 400);
    this.world.rotation.x = -Math.PI / 2; // MuJoCo z (up) -> three y (up)
    this.scene.add(this.world);
    const hemisphere = new THREE.HemisphereLight(0xcfe0ff, 0x3a3430, 1.4);
    this.scene.add(hemisphere);
    this.sun = new THREE.DirectionalLight(0xfff1dc, 2.6);
    this.sun.castShadow = !soft;
    this.sun.shadow.mapSize.set(2048, 2048);
    if (soft) {
      this.blobs = new BlobShadows();
      this.scene.add(this.blobs.group);
    }
    this.sun.shadow.bias = -0.0004;
    this.sun.shadow.normalBias = 0.02;
    this.scene.add(this.sun, this.sun.target);

    // the ground: a plane in MuJoCo's xy plane with a 1 m grid (every 5 m stronger)
    const extent = 4000;
    this.ground = new THREE.Mesh(new THREE.PlaneGeometry(extent, extent), soft ? gridGroundMaterial(groundLight(hemisphere, this.sun, this.sunDir)) : texturedGround(extent));
    this.ground.receiveShadow = true;
    this.ground.name = 'ground';
    this.world.add(this.ground);

    this.controls = new OrbitControls(this.camera, renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.maxPolarAngle = Math.PI * 0.49; // stay above the horizon
    this.controls.addEventListener('change', () => {
      this.dirty = true;
      if (this.userBusy && this.following) this.following.zoom = this.currentZoom();
    });
    this.controls.addEventListener('start', () => (this.userBusy = true));
    this.controls.addEventListener('end', () => (this.userBusy = false));
    this.camera.position.copy(viewDirection(-62, 15).multiplyScalar(10));
    this.resize = new ResizeObserver(() => this.fit());
    this.resize.observe(host);
    this.seen = new IntersectionObserver((entries) => {
      for (const e of entries) this.visible = e.isIntersecting;
      this.dirty = true;
    });
    this.seen.observe(host);
    this.fit();
    this.stopLoop = onFrame((now) => this.render(now));
    viewers.set(renderer.domElement, this);
    window.__neuroRedraw = redraw;
  }

  /** A point in MuJoCo coordinates -> three's world coordinates. */
  toScene(x: number, y: number, z: number): THREE.Vector3 {
    this.world.updateMatrixWorld();
    return new THREE.Vector3(x, y, z).applyMatrix4(this.world.matrixWorld);
  }

  /** The world box of objects in the view (three's frame); hidden objects are left out. */
  boxOf(...objects: THREE.Object3D[]): THREE.Box3 {
    this.world.updateMatrixWorld(true);
    const box = new THREE.Box3();
    for (const o of objects) if (o.visible) box.union(new THREE.Box3().setFromObject(o, false));
    return box;
  }

  setGroundHeight(z: number): void {
    this.groundZ = z;
    this.ground.position.z = z;
    this.dirty = true;
  }

  /** Frame `objects` and `points` (three's world frame), and the ground below them, once, from the
   * usual angle; stops following. */
  frameObjects(
    objects: THREE.Object3D[],
    opts: { points?: THREE.Vector3[]; withGround?: boolean; azimuth?: number; elevation?: number } = {},
  ): void {
    this.following = null;
    const box = this.boxOf(...objects);
    for (const p of opts.points ?? []) box.expandByPoint(p);
    const pts = corners(box);
    if (opts.withGround !== false && !box.isEmpty()) {
      const c = box.getCenter(new THREE.Vector3());
      pts.push(new THREE.Vector3(c.x, this.groundZ, c.z));
    }
    this.frameFit(pts, viewDirection(opts.azimuth ?? -62, opts.elevation ?? 15));
  }

  /** Frame `objects` again, from where the camera looks now, if any part of them is out of view (a
   * goal dragged or typed past the edge). */
  keepInView(objects: THREE.Object3D[]): void {
    const box = this.boxOf(...objects);
    if (box.isEmpty()) return;
    this.camera.updateMatrixWorld();
    const out = corners(box).some((p) => {
      const n = p.clone().project(this.camera);
      return Math.abs(n.x) > 0.98 || Math.abs(n.y) > 0.98 || n.z > 1;
    });
    if (!out) return;
    const pts = corners(box);
    const c = box.getCenter(new THREE.Vector3());
    pts.push(new THREE.Vector3(c.x, this.groundZ, c.z));
    this.frameFit(pts, this.direction());
  }

  /** Keep `box()` (three's world frame) framed as it moves, with the ground below it while it is near;
   * the person may still orbit and zoom. null stops following. */
  follow(box: (() => THREE.Box3 | null) | null, opts: { groundReach?: number; margin?: number } = {}): void {
    if (!box) {
      this.following = null;
      this.framing = '';
      delete this.host.dataset.framing;
      return;
    }
    // never below the ground: a body that falls through it leaves the camera on the ground above it
    const kept = (): THREE.Box3 | null => {
      const b = box();
      return b && aboveGround(b, this.groundZ);
    };
    this.following = { box: kept, zoom: 1, groundReach: opts.groundReach ?? null, margin: opts.margin ?? 0.5 };
    this.followed.set(NaN, NaN, NaN);
    const b = kept();
    if (b && !b.isEmpty()) this.frameFit(this.followPoints(b), this.direction());
  }

  /** The direction from the target to the camera now (unit). */
  private direction(): THREE.Vector3 {
    const dir = this.camera.position.clone().sub(this.controls.target);
    return dir.lengthSq() > 1e-12 ? dir.normalize() : viewDirection(-62, 15);
  }

  /** What a followed box is framed with: itself, and the ground below it while it is within 30 m or a
   * few of its sizes of it (the lander 20 m above its pad is seen with the pad; higher up the model
   * alone, big enough to see, with the horizon for up and down), never less than a couple of metres
   * across (a small model does not fill the view). */
  private followPoints(b: THREE.Box3): THREE.Vector3[] {
    const size = b.getSize(new THREE.Vector3()).length();
    const pts = followPoints(b, this.groundZ, this.following?.groundReach ?? Math.max(30, 6 * size));
    this.framing = `${pts.length > 8 ? 'model and ground' : 'model'} (${(b.min.y - this.groundZ).toFixed(1)} m above the ground)`;
    const c = b.getCenter(new THREE.Vector3());
    const r = Math.max(1, size * (this.following?.margin ?? 0.5));
    pts.push(c.clone().addScalar(r), c.clone().subScalar(r));
    return pts;
  }

  private frameFit(points: THREE.Vector3[], direction: THREE.Vector3): void {
    const f = fitPoints(points, direction, this.camera.fov, this.camera.aspect);
    this.controls.target.copy(f.target);
    this.camera.position.copy(f.target).addScaledVector(direction, f.distance);
    this.setDepthRange(f.distance, this.radiusOf(points, f.target));
    this.controls.update();
    this.dirty = true;
  }

  private radiusOf(points: THREE.Vector3[], c: THREE.Vector3): number {
    return Math.max(0.5, ...points.map((p) => p.distanceTo(c)));
  }

  private setDepthRange(distance: number, radius: number): void {
    this.camera.near = Math.max(0.02, Math.min(distance / 100, (distance - radius) / 4));
    this.camera.far = Math.max(2000, distance * 40);
    this.camera.updateProjectionMatrix();
    const fog = this.scene.fog as THREE.Fog;
    fog.near = Math.max(60, distance * 4);
    fog.far = Math.max(400, distance * 25);
  }

  private currentZoom(): number {
    const f = this.following;
    const b = f?.box();
    if (!f || !b || b.isEmpty()) return 1;
    const auto = fitPoints(this.followPoints(b), this.direction(), this.camera.fov, this.camera.aspect).distance;
    return this.camera.position.distanceTo(this.controls.target) / auto;
  }

  /** Keep the sun's shadow camera on what is framed, so shadows stay sharp wherever the model goes. */
  private aimSun(center: THREE.Vector3, radius: number): void {
    const r = Math.min(Math.max(radius * 1.3, 3), 300);
    this.sun.position.copy(center).addScaledVector(this.sunDir, r * 3);
    this.sun.target.position.copy(center);
    const cam = this.sun.shadow.camera;
    if (cam.right !== r) {
      cam.left = -r;
      cam.right = r;
      cam.top = r;
      cam.bottom = -r;
      cam.near = 0.1;
      cam.far = r * 6;
      cam.updateProjectionMatrix();
    }
  }

  /** Tests and people alike: `data-screen-<name>="x,y,on,w,h"` on the view's host, in CSS pixels of the
   * canvas, for the object `get()` returns: where its middle is, whether that is in view, and how wide
   * and tall its box is drawn (refreshed four times a second). */
  mark(name: string, get: () => THREE.Object3D | null): () => void {
    this.marks.set(name, get);
    return () => {
      this.marks.delete(name);
      delete this.host.dataset[`screen${name[0]!.toUpperCase()}${name.slice(1)}`];
    };
  }

  /** Where a MuJoCo point is on the canvas (CSS pixels) and whether it is inside the view. */
  screenOf(p: THREE.Vector3): { x: number; y: number; on: boolean } {
    const n = p.clone().project(this.camera);
    const w = this.host.clientWidth;
    const h = this.host.clientHeight;
    return { x: ((n.x + 1) / 2) * w, y: ((1 - n.y) / 2) * h, on: Math.abs(n.x) <= 1 && Math.abs(n.y) <= 1 && n.z < 1 };
  }

  /** Draws the scene as it is now and writes its marks (data-screen-*) for that very picture. */
  drawNow(): void {
    this.blobs?.update(this.world, this.groundZ);
    this.renderer.render(this.scene, this.camera);
    this.writeMarks(performance.now(), true);
  }

  private writeMarks(now: number, always = false): void {
    if (!always && now - this.lastMarks < 250) return;
    this.lastMarks = now;
    if (this.framing) this.host.dataset.framing = this.framing;
    for (const [name, get] of this.marks) {
      const o = get();
      const key = `screen${name[0]!.toUpperCase()}${name.slice(1)}`;
      if (!o) {
        delete this.host.dataset[key];
        continue;
      }
      const box = new THREE.Box3().setFromObject(o);
      const c = box.isEmpty() ? o.getWorldPosition(new THREE.Vector3()) : box.getCenter(new THREE.Vector3());
      const s = this.screenOf(c);
      const drawn = corners(box).map((p) => this.screenOf(p));
      const w = drawn.length ? Math.max(...drawn.map((p) => p.x)) - Math.min(...drawn.map((p) => p.x)) : 0;
      const h = drawn.length ? Math.max(...drawn.map((p) => p.y)) - Math.min(...drawn.map((p) => p.y)) : 0;
      this.host.dataset[key] = `${s.x.toFixed(0)},${s.y.toFixed(0)},${s.on ? 1 : 0},${w.toFixed(0)},${h.toFixed(0)}`;
    }
  }

  invalidate(): void {
    this.dirty = true;
  }

  onBeforeRender(f: (now: number) => void): () => void {
    this.beforeRender.add(f);
    return () => this.beforeRender.delete(f);
  }

  private fit(): void {
    const w = Math.max(1, this.host.clientWidth);
    const h = Math.max(1, this.host.clientHeight);
    this.scale = resolutionScale();
    this.renderer.setPixelRatio(this.basePixelRatio * this.scale);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  private render(now: number): void {
    const dt = this.lastRender ? Math.min(0.25, (now - this.lastRender) / 1000) : 0;
    this.lastRender = now;
    for (const f of this.beforeRender) f(now); // the clocks run on while the view is scrolled away
    if (!this.visible) return;
    if (resolutionScale() !== this.scale) this.fit();
    const f = this.following;
    const b = f?.box();
    if (f && b && !b.isEmpty()) {
      // glide towards the framing at the same pace whatever the frame rate (about 8 % per 60 Hz frame)
      const pts = this.followPoints(b);
      const dir = this.direction();
      const fit = fitPoints(pts, dir, this.camera.fov, this.camera.aspect);
      const k = 1 - Math.pow(0.92, dt * 60);
      const now = this.camera.position.distanceTo(this.controls.target);
      const dist = now + (fit.distance * f.zoom - now) * (this.userBusy ? 0 : k);
      // move with the model at once (however fast it goes, it stays where it was in the view), and
      // glide towards the new framing when what is framed changes (the ground comes into it)
      const centre = b.getCenter(new THREE.Vector3());
      const target = this.controls.target.clone();
      if (Number.isFinite(this.followed.x)) target.add(centre.clone().sub(this.followed));
      this.followed.copy(centre);
      target.lerp(fit.target, k);
      this.controls.target.copy(target);
      this.camera.position.copy(target).addScaledVector(dir, dist);
      const radius = this.radiusOf(pts, fit.target);
      this.setDepthRange(dist, radius);
      this.aimSun(fit.target, radius);
      this.dirty = true;
    } else {
      this.aimSun(this.controls.target, this.camera.position.distanceTo(this.controls.target) * 0.6);
    }
    this.controls.update();
    this.sky.position.copy(this.camera.position);
    this.sky.scale.setScalar(this.camera.far * 0.9);
    this.writeMarks(now);
    if (!this.dirty && !this.animating) return;
    this.dirty = false;
    this.blobs?.update(this.world, this.groundZ);
    this.renderer.render(this.scene, this.camera);
  }

  dispose(): void {
    this.stopLoop();
    this.resize.disconnect();
    this.seen.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
    this.renderer.domElement.remove();
  }
}
