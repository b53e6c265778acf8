// Replaying a controller: the emulated and the physical (MuJoCo) trajectories side by side, each with
// the translucent goal and its path, interpolated between super-steps at the display rate; the
// emulator's side also shows MuJoCo as a cyan outline, and the gap between them is plotted over time.
// Above them, the job's outcome: its success criterion and each check on both sides.
import * as THREE from 'three';
import type { LayoutGroup, ModelGeometry } from '../api/emulator.gen';
import type { EmulatorApi } from '../api/emulator';
import type { JobResult } from '../api/controller';
import { gapLabel, poseGap, rootMoves, type Gap } from '../scene/divergence';
import { locate, lerpPoses, type Pose } from '../scene/interp';
import { acrossPath, replayWindow } from '../scene/camera';
import { groundHeight, ModelView } from '../scene/model';
import type { MeshFiles } from '../scene/meshes';
import { makeViewer, meshFilesOf } from '../scene/setup';
import { DropLine, Trail } from '../scene/trail';
import type { Viewer } from '../scene/viewer';
import { hasGoalState } from '../session/target';
import { h } from '../ui/dom';
import { DivergencePanel, GHOST_LOOK, GOAL_COLOR, MODEL_TRAIL } from './divergence';
import { outcomeView } from './outcome';

// how many of the body's sizes a replay's view spans at most: the body stays a fifth of it or more
const BODY_SIZES_IN_VIEW = 4;

/** Rows with a non-finite value (a diverged physics run) are replaced by the last finite row. */
export function finiteRows(states: (number | null)[][]): number[][] {
  const out: number[][] = [];
  for (const row of states) {
    const ok = row.every((v) => v !== null && Number.isFinite(v));
    const prev = out[out.length - 1];
    if (ok) out.push(row as number[]);
    else if (prev) out.push(prev);
  }
  return out;
}

interface Side {
  viewer: Viewer;
  model: ModelView;
  drop: DropLine | null;
  poses: Pose[][];
  ghost: { view: ModelView; poses: Pose[][] } | null;
}

export class Replay {
  readonly el: HTMLElement;
  private readonly views: Side[] = [];
  private times: number[] = [];
  private gaps: (Gap | null)[] = [];
  private t = 0;
  private playing = true;
  private last = 0;
  private lastPanel = 0;
  private readonly slider: HTMLInputElement;
  private readonly clock: HTMLElement;
  private readonly playBtn: HTMLButtonElement;
  private readonly divergence = new DivergencePanel('replay-divergence', { marker: true });
  private stops: (() => void)[] = [];
  private disposables: { dispose(): void }[] = [];
  private readonly files: MeshFiles;

  constructor(
    private readonly api: EmulatorApi,
    private readonly geometry: ModelGeometry,
    private readonly layout: LayoutGroup[],
    private readonly result: JobResult,
    private readonly superTimestep: number,
  ) {
    this.files = meshFilesOf(api, geometry);
    this.playBtn = h('button', { id: 'replay-play' }, 'Pause');
    this.slider = h('input', { type: 'range', min: 0, max: 1, step: 0.001, value: 0, id: 'replay-time', 'aria-label': 'replay time' });
    this.clock = h('span', { class: 'clock', id: 'replay-clock' }, '');
    this.el = h('section', { class: 'card replay', id: 'replay' }, h('h2', {}, 'Replay'));
    this.playBtn.addEventListener('click', () => {
      this.playing = !this.playing;
      if (this.playing && this.t >= this.end) this.t = 0;
      this.playBtn.textContent = this.playing ? 'Pause' : 'Play';
    });
    this.slider.addEventListener('input', () => {
      this.t = Number(this.slider.value) * this.end;
      this.playing = false;
      this.playBtn.textContent = 'Play';
    });
  }

  private get end(): number {
    return this.times[this.times.length - 1] ?? 0;
  }

  async start(): Promise<void> {
    const r = this.result;
    const model = this.geometry.model;
    const emulated = finiteRows(r.emulated?.states ?? []);
    const physical = finiteRows(r.physical?.states ?? []);
    // the goal, where the objective has one (dolphin-swim's has no goal state: as far as it can)
    const aimed = hasGoalState(r.spec?.state_weights);
    const target = aimed && r.target_state && r.target_state.every((v) => v !== null) ? (r.target_state as number[]) : null;
    const [pe, pp, pt] = await Promise.all([
      emulated.length ? this.api.poses(model, emulated, r.version ?? undefined) : null,
      physical.length ? this.api.poses(model, physical, r.version ?? undefined) : null,
      target ? this.api.poses(model, [target], r.version ?? undefined) : null,
    ]);
    const n = Math.max(emulated.length, physical.length);
    const times = r.times && r.times.length === n ? r.times : Array.from({ length: n }, (_, i) => i * this.superTimestep);
    this.times = times;
    const rooted = rootMoves(this.layout);
    const goalPoses = pt?.poses[0] ?? null;
    const row = h('div', { class: 'replay-views' });
    this.el.append(outcomeView(r), row, h('div', { class: 'replay-bar' }, this.playBtn, this.slider, this.clock), this.divergence.el);
    const sides: [string, Pose[][] | undefined, Pose[][] | undefined][] = [
      ['Emulator', pe?.poses, pp?.poses],
      ['MuJoCo (physics)', pp?.poses, undefined],
    ];
    // one ground height for both sides: the model standing at its lowest over both runs and the goal
    const probe = new ModelView(this.geometry);
    const ground = groundHeight(probe, [...(pe?.poses ?? []), ...(pp?.poses ?? []), ...(goalPoses ? [goalPoses] : [])]);
    probe.dispose();
    for (const [title, poses, ghostPoses] of sides) {
      const host = h('div', { class: 'view replay-view', 'data-side': title });
      row.append(h('div', { class: 'replay-side' }, h('h3', {}, title), host));
      if (!poses?.length) {
        host.append(h('p', { class: 'muted' }, 'No trajectory.'));
        continue;
      }
      const viewer = makeViewer(host);
      if (!viewer) continue;
      const view = new ModelView(this.geometry, {}, this.files);
      viewer.world.add(view.group);
      const framed: THREE.Object3D[] = [view.group];
      let goal: ModelView | null = null;
      if (goalPoses) {
        goal = new ModelView(this.geometry, { ghost: true, color: GOAL_COLOR, opacity: 0.3 }, this.files);
        goal.setPoses(goalPoses);
        viewer.world.add(goal.group);
        framed.push(goal.group);
        this.disposables.push(goal);
      }
      let ghost: Side['ghost'] = null;
      if (ghostPoses?.length) {
        // an outline with the faintest faces: the emulator's body under it keeps its own colours
        const g = new ModelView(this.geometry, GHOST_LOOK, this.files);
        viewer.world.add(g.group);
        ghost = { view: g, poses: ghostPoses };
        this.disposables.push(g);
      }
      // the whole path, for the framing and drawn as the trail
      const path = poses.map((p) => p[rooted ? 0 : p.length - 1] ?? [0, 0, 0]);
      const trail = new Trail(MODEL_TRAIL, Math.max(2, path.length));
      trail.set(path);
      viewer.world.add(trail.line);
      this.disposables.push(trail);
      view.setPoses(poses[0] ?? []);
      viewer.setGroundHeight(ground);
      const drop = rooted ? new DropLine(MODEL_TRAIL) : null;
      if (drop) {
        viewer.world.add(drop.group);
        this.disposables.push(drop);
      }
      // seen across the path (a turn is not foreshortened, a descent is seen from the side), framing
      // the path, its goal and the body at both ends; on a path many times the body's size the camera
      // keeps a window of a few body sizes around the body instead, slid along the path as it moves
      const points = path.map((p) => viewer.toScene(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0));
      const across = acrossPath(path.map((p) => new THREE.Vector3(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0)));
      viewer.frameObjects(framed, { points, ...across });
      const region = viewer.boxOf(...framed);
      view.setPoses(poses[poses.length - 1] ?? []);
      region.union(viewer.boxOf(...view.moving));
      for (const p of points) region.expandByPoint(p);
      view.setPoses(poses[0] ?? []);
      const body = viewer.boxOf(...view.moving).getSize(new THREE.Vector3());
      const window = BODY_SIZES_IN_VIEW * Math.max(body.x, body.y, body.z, 0.2);
      // the window is what is framed (no room added around it), the ground only where the path goes
      viewer.follow(() => replayWindow(viewer.boxOf(...view.moving), region, window), { groundReach: 0, margin: 0 });
      viewer.animating = true;
      this.stops.push(viewer.mark('model', () => view.root), viewer.mark('goal', () => goal?.root ?? null));
      this.views.push({ viewer, model: view, drop, poses, ghost });
    }
    if (pe?.poses.length && pp?.poses.length) {
      this.gaps = times.map((_, i) => {
        const a = pe.poses[Math.min(i, pe.poses.length - 1)];
        const b = pp.poses[Math.min(i, pp.poses.length - 1)];
        return a && b ? poseGap(a, b, rooted) : null;
      });
      this.divergence.configure(gapLabel(this.layout), true);
      this.divergence.setAll(times, this.gaps);
    }
    const first = this.views[0];
    if (first) this.stops.push(first.viewer.onBeforeRender((now) => this.tick(now)));
  }

  private tick(now: number): void {
    const dt = this.last ? (now - this.last) / 1000 : 0;
    this.last = now;
    if (this.playing) {
      this.t = Math.min(this.end, this.t + dt);
      if (this.t >= this.end) {
        this.playing = false;
        this.playBtn.textContent = 'Play';
      }
      this.slider.value = String(this.end > 0 ? this.t / this.end : 0);
    }
    const { i, f } = locate(this.times, this.t);
    const at = (poses: Pose[][]): Pose[] | null => {
      const a = poses[Math.min(i, poses.length - 1)];
      const b = poses[Math.min(i + 1, poses.length - 1)];
      return a && b ? lerpPoses(a, b, f) : null;
    };
    for (const v of this.views) {
      const p = at(v.poses);
      if (p) v.model.setPoses(p);
      const root = p?.[0];
      if (root && v.drop) v.drop.set(root[0] ?? 0, root[1] ?? 0, root[2] ?? 0, v.viewer.groundZ);
      const g = v.ghost ? at(v.ghost.poses) : null;
      if (g && v.ghost) v.ghost.view.setPoses(g);
    }
    if (now - this.lastPanel > 100) {
      this.lastPanel = now;
      this.divergence.show(this.gaps[Math.min(i + (f > 0.5 ? 1 : 0), this.gaps.length - 1)] ?? null);
      this.divergence.mark(this.t);
    }
    this.clock.textContent = `${this.t.toFixed(1)} / ${this.end.toFixed(1)} s`;
    this.el.dataset.t = this.t.toFixed(2);
  }

  dispose(): void {
    for (const s of this.stops) s();
    for (const d of this.disposables) d.dispose();
    for (const v of this.views) {
      v.model.dispose();
      v.viewer.dispose();
    }
    this.views.length = 0;
    this.divergence.dispose();
    this.el.remove();
  }
}
