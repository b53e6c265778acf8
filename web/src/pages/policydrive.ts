// Drive a stored policy: pick one (GET /policies), start an emulator session driven by it (POST
// /sessions with `policy`), and watch it over the real-time websocket beside its MuJoCo ghost (the same
// policy flying the physics). The goal is a translucent green copy of the model where the goal puts it
// (the task's target state with the goal in place), dragged in the view on the ground (the lander's
// pad, the truck's spot) or on a horizontal plane at its height (the quadrotor's target; a slider sets
// the height), or set with sliders (the pendulum's three angles, the truck's heading, the runner's
// speed: a command, which has no marker); every change
// goes to the session as `goal` in a websocket `controls` message. The replies' `goal_outside` is
// shown when the goal leaves the range the policy was trained for. "Kick" perturbs the velocities:
// the emulator service cannot set a live session's state, so a new session of the same policy and goal
// starts from the kicked state (its ghost with it); models with force inputs also get push sliders.
import * as THREE from 'three';
import type { PolicyManifest } from '../api/controller';
import type { ModelDetail, ModelGeometry, SessionInfo, WsState } from '../api/emulator.gen';
import { errorText } from '../api/http';
import { goalHandles, goalOutside, goalPoint, goalState, kicked, movedGoal, roundGoal, sameGoal, sliderRange, timeToCheck, type GoalHandles, type GoalKind } from '../policies/goal';
import { controlsLine, percent } from '../policies/progress';
import { gapLabel, poseGap, rootMoves } from '../scene/divergence';
import { dragGoal } from '../scene/goaldrag';
import type { Pose } from '../scene/interp';
import { groundHeight, ModelView } from '../scene/model';
import { makeViewer, meshFilesOf } from '../scene/setup';
import { DropLine, Trail } from '../scene/trail';
import type { Viewer } from '../scene/viewer';
import { envelopeText, RealtimeSession } from '../session/realtime';
import { startFromQuery } from '../session/start';
import { fmt, h } from '../ui/dom';
import { clearNotice, notify } from '../ui/notices';
import type { Ctx } from './context';
import { DivergencePanel, GHOST_COLOR, GHOST_LOOK, GOAL_COLOR, MODEL_TRAIL } from './divergence';

/** Whether a goal of this kind is a place, drawn and dragged in the view. */
const isPlace = (kind: GoalKind): boolean => kind === 'ground' || kind === 'space';

/** What the view marks as the goal (for the tests): the place's handle, the pose's outline; a command
 * has none. */
function goalMark(s: Scene | null): THREE.Object3D | null {
  if (!s || s.handles.kind === 'command') return null;
  return s.handles.kind === 'pose' ? s.marker.group : s.pick;
}

const GOAL_SEND_MS = 100; // a goal dragged is sent at most this often (and once more where it is let go)
const GOAL_LOOK = { ghost: true, color: GOAL_COLOR, opacity: 0.25 } as const;

/** What is drawn for one policy's session: it outlives the sessions a kick starts. */
interface Scene {
  policy: PolicyManifest;
  detail: ModelDetail;
  geometry: ModelGeometry;
  handles: GoalHandles;
  base: number[]; // the state the goal is drawn in: the task's target state (else the start)
  goal: number[];
  placed: [number, number, number] | null; // the goal's point when the marker's poses were last set
  model: ModelView;
  ghost: ModelView;
  marker: ModelView;
  pick: THREE.Mesh; // what a press on the goal hits, around the goal's point
  pad: DropLine; // the goal's point on the ground
  drop: DropLine; // below the emulated model
  trail: Trail;
  ghostTrail: Trail;
  rooted: boolean;
  forces: number[];
  inputs: { slider: HTMLInputElement; number: HTMLInputElement; value: HTMLElement; row: HTMLElement }[];
}

/** One session of the scene's policy (a kick replaces it). */
interface Conn {
  info: SessionInfo;
  socket: RealtimeSession;
  echoed: number[] | null; // the goal the replies carry
  goalStep: number; // the super-step the echoed goal was set at (a timed policy's clock)
}

export class DrivePanel {
  readonly aside: HTMLElement;
  readonly stage: HTMLElement;
  private readonly select = h('select', { id: 'pd-policy', 'aria-label': 'policy' });
  private readonly about = h('p', { class: 'desc', id: 'pd-about' }, 'Loading the stored policies…');
  private readonly startBtn = h('button', { id: 'pd-start', class: 'primary', disabled: true }, 'Start session');
  private readonly stopBtn = h('button', { id: 'pd-stop', disabled: true }, 'Stop');
  private readonly ghostBox = h('input', { type: 'checkbox', id: 'pd-ghost', checked: true });
  private readonly goalHint = h('p', { class: 'hint', id: 'pd-goal-hint' });
  private readonly goalEditor = h('div', { class: 'goal-editor', id: 'pd-goal' });
  private readonly outside = h('div', { class: 'envelope', id: 'pd-goal-outside', hidden: true });
  private readonly envelope = h('div', { class: 'envelope', id: 'pd-envelope', hidden: true });
  private readonly kickBtn = h('button', { id: 'pd-kick', disabled: true }, 'Kick');
  private readonly disturb = h('div', { class: 'disturb', id: 'pd-disturb' });
  private readonly status = h('div', { class: 'status', id: 'pd-status' }, 'No session. Pick a policy and start one.');
  private readonly viewHost = h('div', { class: 'view', id: 'pd-view' });
  private readonly divergence = new DivergencePanel('pd-divergence', { overlay: true });
  private viewer: Viewer | null = null;
  private policies: PolicyManifest[] = [];
  private scene: Scene | null = null;
  private conn: Conn | null = null;
  private alive = true;
  private placing = 0; // the latest request for the marker's poses
  private placeTimer = 0;
  private sentAt = 0;
  private sentText = '';
  private dragging = false;
  private lastStatus = 0;
  private readonly stops: (() => void)[] = [];

  constructor(private readonly ctx: Ctx) {
    this.aside = h(
      'aside',
      { class: 'panel' },
      h('label', {}, 'Policy ', this.select),
      this.about,
      h('div', { class: 'buttons' }, this.startBtn, this.stopBtn),
      h('label', { class: 'check' }, this.ghostBox, ' Show the MuJoCo ghost (the same policy flying the physics)'),
      h(
        'p',
        { class: 'legend' },
        h('span', { class: 'swatch solid' }),
        'emulator ',
        h('span', { class: 'swatch ghost' }),
        'MuJoCo ghost ',
        h('span', { class: 'swatch goal' }),
        'goal ',
        h('span', { class: 'swatch trail' }),
        'trail',
      ),
      h('h3', {}, 'Goal'),
      this.goalHint,
      this.goalEditor,
      this.outside,
      h('h3', {}, 'Disturb it'),
      this.disturb,
      this.envelope,
      this.status,
    );
    this.stage = h('div', { class: 'stage' }, this.viewHost, this.divergence.el);
    this.startBtn.addEventListener('click', () => void this.start());
    this.stopBtn.addEventListener('click', () => {
      void this.stop();
      this.status.textContent = 'Session stopped.';
    });
    this.select.addEventListener('change', () => this.describe());
    this.ghostBox.addEventListener('change', () => {
      const on = this.ghostBox.checked;
      this.conn?.socket.setShadow(on);
      if (this.scene) {
        this.scene.ghost.visible = on;
        this.scene.ghostTrail.clear();
      }
      this.divergence.reset(on && !!this.scene);
    });
    this.kickBtn.addEventListener('click', () => void this.kick());
  }

  /** Makes the view (its host is in the page now) and lists the policies; `wanted` ("model/name") is
   * selected, and started when `drive`. */
  async open(wanted: string | null, drive: boolean): Promise<void> {
    this.viewer = makeViewer(this.viewHost);
    const v = this.viewer;
    if (v) {
      this.stops.push(
        dragGoal(v, {
          targets: () => (this.scene && isPlace(this.scene.handles.kind) && this.conn ? [this.scene.pick, this.scene.marker.group] : null),
          at: () => (this.scene ? this.point(this.scene) : null),
          began: () => {
            this.dragging = true;
            v.follow(null);
          },
          moved: (x, y) => this.moveGoal(x, y),
          done: (x, y) => {
            this.dragging = false;
            this.moveGoal(x, y);
            this.sendGoal(true);
            if (this.scene) v.follow(this.framed(this.scene));
          },
        }),
        v.mark('model', () => this.scene?.model.root ?? null),
        v.mark('ghost', () => (this.scene?.ghost.visible ? this.scene.ghost.root : null)),
        v.mark('goal', () => goalMark(this.scene)),
        v.onBeforeRender((now) => this.frame(now)),
      );
    }
    await this.refresh(wanted);
    if (drive && this.alive && this.selected()) await this.start();
  }

  /** Lists the stored policies again (a job just stored one), keeping or choosing `wanted`. */
  async refresh(wanted: string | null = null): Promise<void> {
    try {
      const list = await this.ctx.controller.policies();
      if (!this.alive) return;
      const keep = wanted ?? this.select.value;
      this.policies = list;
      this.select.textContent = '';
      this.select.append(...list.map((p) => h('option', { value: `${p.model}/${p.name}` }, `${p.name} (${p.model}, ${p.version})`)));
      if (list.some((p) => `${p.model}/${p.name}` === keep)) this.select.value = keep;
      this.startBtn.disabled = !list.length;
      this.describe();
      clearNotice('policies');
    } catch (e) {
      this.about.textContent = 'No policies: the controller service did not answer.';
      notify(`Cannot list the stored policies. ${errorText(e)}`, 'error', 'policies');
    }
  }

  private selected(): PolicyManifest | undefined {
    return this.policies.find((p) => `${p.model}/${p.name}` === this.select.value);
  }

  private describe(): void {
    const p = this.selected();
    if (!p) {
      this.about.textContent = 'No stored policies yet: train one below.';
      return;
    }
    const m = p.metrics ?? {};
    const how =
      typeof m.return_physics === 'number'
        ? `its episodes on MuJoCo earned a return of ${fmt(m.return_physics)} (mean of ${m.evaluate_runs ?? '?'})`
        : `it met the task on MuJoCo in ${percent(m.success_physics)} of ${m.evaluate_runs ?? '?'} held-out runs`;
    this.about.textContent = `${p.description ? `${p.description.replace(/\.?$/, '.')} ` : ''}Trained through ${p.model} ${p.emulator_version}; ${how}.`;
    this.about.dataset.successPhysics = String(m.success_physics ?? '');
  }

  // ---------------------------------------------------------------- sessions
  async start(): Promise<void> {
    await this.stop();
    const p = this.selected();
    if (!p) return;
    this.startBtn.disabled = true;
    this.status.textContent = `Starting a ${p.model} session driven by ${p.name}…`;
    try {
      const version = p.emulator_version;
      const [detail, geometry] = await Promise.all([this.ctx.emulator.model(p.model, version), this.ctx.emulator.geometry(p.model, version)]);
      const goal = roundGoal(p.goal_default);
      const { seed } = startFromQuery(location.hash.split('?')[1] ?? '');
      const info = await this.ctx.emulator.createSession({ model: p.model, policy: { name: p.name, version: p.version, goal }, ...(seed !== null ? { seed } : {}) });
      if (!this.alive) {
        void this.ctx.emulator.deleteSession(info.id).catch(() => undefined);
        return;
      }
      const target = p.task?.target_state;
      const base = Array.isArray(target) && target.length === detail.state_size ? (target as number[]) : info.state;
      this.scene = this.build(p, detail, geometry, base, goal);
      this.connect(info);
      await this.place(true);
      this.stopBtn.disabled = false;
      clearNotice('drive');
    } catch (e) {
      this.status.textContent = 'No session.';
      notify(`Could not start a session driven by ${p.name}. ${errorText(e)}`, 'error', 'drive');
      await this.stop();
    } finally {
      this.startBtn.disabled = !this.policies.length;
    }
  }

  async stop(): Promise<void> {
    const c = this.conn;
    this.conn = null;
    this.stopBtn.disabled = true;
    this.kickBtn.disabled = true;
    window.clearTimeout(this.placeTimer);
    if (this.scene) this.disposeScene(this.scene);
    this.scene = null;
    this.goalEditor.textContent = '';
    this.disturb.textContent = '';
    this.goalHint.textContent = '';
    this.outside.hidden = true;
    this.envelope.hidden = true;
    this.envelope.textContent = '';
    this.divergence.reset(false);
    clearNotice('envelope');
    if (!c) return;
    c.socket.close();
    try {
      await this.ctx.emulator.deleteSession(c.info.id);
    } catch {
      /* expired or the service is gone: nothing to clean up */
    }
  }

  private connect(info: SessionInfo): void {
    const shadow = this.ghostBox.checked;
    const conn: Conn = { info, echoed: info.policy?.goal ?? null, goalStep: info.steps, socket: null as unknown as RealtimeSession };
    conn.socket = new RealtimeSession(this.ctx.emulator.socketUrl(info.id, `mode=realtime&poses=true${shadow ? '&shadow=true' : ''}`), {
      onState: (msg) => this.onState(conn, msg),
      onError: (text, code) => {
        notify(text, 'error', 'drive');
        if (code === 'diverged' || code === 'unknown_session') void this.stop();
      },
      onClose: (text) => {
        notify(text, 'error', 'drive');
        if (this.conn === conn) void this.stop();
      },
    });
    this.conn = conn;
    this.sentAt = 0;
    this.sentText = '';
    this.sendGoal(true);
  }

  private onState(conn: Conn, msg: WsState): void {
    if (this.conn !== conn) return;
    const s = this.scene;
    if (msg.goal && !sameGoal(msg.goal, conn.echoed)) {
      conn.echoed = msg.goal;
      conn.goalStep = msg.steps;
    }
    if (this.kickBtn.disabled) this.kickBtn.disabled = false;
    if (s && msg.poses && msg.shadow?.poses && s.ghost.visible) {
      const gap = poseGap(msg.poses, msg.shadow.poses, s.rooted);
      if (gap) this.divergence.add(msg.t, gap);
    }
    // the goal outside the trained range, as the service says it of the goal it holds
    const out = msg.goal_outside ?? [];
    const text = out.length && s ? `The goal is outside the range ${s.policy.name} was trained for: ${this.rangeText(s, out)}. The policy was not trained there: expect it to do worse.` : '';
    if ((this.outside.textContent ?? '') !== text) {
      this.outside.textContent = text;
      this.outside.hidden = !text;
      this.outside.dataset.outside = out.join(',');
    }
    const env = envelopeText(msg);
    if ((this.envelope.textContent ?? '') !== (env ?? '')) {
      this.envelope.hidden = !env;
      this.envelope.textContent = env ?? '';
      if (env) notify(`The session left the emulator's trained envelope: ${env}. Its states are extrapolated.`, 'warning', 'envelope');
      else clearNotice('envelope');
    }
  }

  private rangeText(s: Scene, names: string[]): string {
    const p = s.policy;
    return names
      .map((n) => {
        const i = p.goal_variables.indexOf(n);
        return i < 0 ? n : `${n} ${fmt(s.goal[i])} (trained ${fmt(p.goal_low[i])} … ${fmt(p.goal_high[i])})`;
      })
      .join(', ');
  }

  /** A kick: the velocities of the latest state perturbed, and a new session of the same policy and
   * goal from there (the ghost restarts from it too). */
  private async kick(): Promise<void> {
    const s = this.scene;
    const c = this.conn;
    const last = c?.socket.last;
    if (!s || !c || !last) return;
    this.kickBtn.disabled = true;
    const state = kicked(last.state, s.detail.layout, s.detail.envelope, Math.random);
    try {
      const p = s.policy;
      const info = await this.ctx.emulator.createSession({ model: p.model, state, policy: { name: p.name, version: p.version, goal: roundGoal(s.goal) } });
      if (this.scene !== s || this.conn !== c) {
        void this.ctx.emulator.deleteSession(info.id).catch(() => undefined);
        return;
      }
      c.socket.close();
      void this.ctx.emulator.deleteSession(c.info.id).catch(() => undefined);
      this.connect(info);
      this.status.dataset.kicks = String(Number(this.status.dataset.kicks ?? '0') + 1);
      this.status.dataset.kicked = JSON.stringify(state.map((v) => Number(v.toPrecision(4))));
    } catch (e) {
      notify(`Could not kick the session. ${errorText(e)}`, 'error', 'drive');
    } finally {
      this.kickBtn.disabled = !this.conn;
    }
  }

  // ---------------------------------------------------------------- the goal
  private point(s: Scene): [number, number, number] | null {
    return goalPoint(goalState(s.base, s.handles, s.goal), s.handles);
  }

  private moveGoal(x: number, y: number): void {
    const s = this.scene;
    if (!s) return;
    s.goal = movedGoal(s.goal, s.handles, x, y);
    this.showGoal(s);
  }

  /** A goal variable typed or slid. Moving the root's place moves the marker as it is; any other
   * variable (a heading, a joint angle) changes its pose, which the service works out. */
  private setGoalValue(i: number, v: number, from: HTMLInputElement): void {
    const s = this.scene;
    if (!s || !Number.isFinite(v)) return;
    s.goal = [...s.goal];
    s.goal[i] = v;
    this.showGoal(s, from);
    const h = s.handles;
    if (h.kind !== 'command' && i !== h.x && i !== h.y && i !== h.z) {
      window.clearTimeout(this.placeTimer);
      this.placeTimer = window.setTimeout(() => void this.place(), 120);
    }
    this.sendGoal(false);
  }

  /** The inputs show the goal (all but the one being moved, `from`), and whether each value is inside
   * the trained range. */
  private showGoal(s: Scene, from: HTMLInputElement | null = null): void {
    const p = s.policy;
    const out = new Set(goalOutside(s.goal, p.goal_low, p.goal_high, p.goal_variables));
    s.inputs.forEach((inp, i) => {
      const v = s.goal[i] ?? 0;
      if (inp.slider !== from) inp.slider.value = String(v);
      if (inp.number !== from) inp.number.value = v.toFixed(2);
      inp.value.textContent = fmt(v);
      inp.row.classList.toggle('outside', out.has(p.goal_variables[i] ?? ''));
    });
    this.goalEditor.dataset.goal = JSON.stringify(roundGoal(s.goal));
    this.viewer?.invalidate();
  }

  /** The goal to the session: at most every GOAL_SEND_MS while it moves, at once when `now`. */
  private sendGoal(now: boolean): void {
    const s = this.scene;
    const c = this.conn;
    if (!s || !c) return;
    const t = performance.now();
    if (!now && t - this.sentAt < GOAL_SEND_MS) return;
    this.sentAt = t;
    const goal = roundGoal(s.goal);
    const text = JSON.stringify([goal, s.forces]);
    if (text === this.sentText) return; // (the socket sends only changes too; this spares the page a write)
    this.sentText = text;
    c.socket.setGoal(goal, s.forces);
    this.status.dataset.sent = JSON.stringify(goal);
  }

  /** Poses the marker at the goal (the service works out the model's bodies in the goal state). */
  private async place(first = false): Promise<void> {
    const s = this.scene;
    if (!s) return;
    const n = ++this.placing;
    if (s.handles.kind === 'command') {
      // no marker: the ground under the model as it starts, and the camera on it
      if (first && this.viewer) {
        this.viewer.setGroundHeight(groundHeight(s.model, [s.geometry.rest_poses]));
        this.viewer.follow(this.framed(s));
      }
      return;
    }
    const state = goalState(s.base, s.handles, s.goal);
    try {
      const r = await this.ctx.emulator.poses(s.detail.model, [state], s.detail.version);
      if (this.scene !== s || n !== this.placing) return;
      const poses = r.poses[0] ?? [];
      s.marker.setPoses(poses);
      s.placed = goalPoint(state, s.handles);
      s.marker.group.position.set(0, 0, 0);
      if (first && this.viewer) {
        // the ground below the model where it stands at its goal (a landed lander on its pad)
        this.viewer.setGroundHeight(groundHeight(s.model, [s.geometry.rest_poses, poses]));
        const size = this.viewer.boxOf(s.marker.group).getSize(new THREE.Vector3()).length();
        s.pick.scale.setScalar(Math.min(3, Math.max(0.5, size / 2)));
        this.viewer.follow(this.framed(s));
      }
      this.viewer?.invalidate();
    } catch (e) {
      notify(`Cannot place the goal. ${errorText(e)}`, 'error', 'goal');
    }
  }

  // ---------------------------------------------------------------- the scene
  private build(p: PolicyManifest, detail: ModelDetail, geometry: ModelGeometry, base: number[], goal: number[]): Scene {
    const files = meshFilesOf(this.ctx.emulator, geometry);
    const handles = goalHandles(p.goal_variables, detail.state_labels, detail.layout);
    const pick = new THREE.Mesh(new THREE.SphereGeometry(1, 16, 12), new THREE.MeshBasicMaterial({ color: GOAL_COLOR, transparent: true, opacity: 0, depthWrite: false }));
    pick.name = 'goal-pick';
    pick.visible = isPlace(handles.kind);
    const s: Scene = {
      policy: p,
      detail,
      geometry,
      handles,
      base,
      goal,
      placed: null,
      model: new ModelView(geometry, {}, files),
      ghost: new ModelView(geometry, GHOST_LOOK, files),
      marker: new ModelView(geometry, GOAL_LOOK, files),
      pick,
      pad: new DropLine(GOAL_COLOR, 0.9),
      drop: new DropLine(MODEL_TRAIL),
      trail: new Trail(MODEL_TRAIL),
      ghostTrail: new Trail(GHOST_COLOR),
      rooted: rootMoves(detail.layout),
      forces: detail.forces.map(() => 0),
      inputs: [],
    };
    s.ghost.visible = this.ghostBox.checked;
    s.drop.group.visible = s.rooted;
    s.pad.group.visible = isPlace(handles.kind);
    s.marker.visible = handles.kind !== 'command';
    this.divergence.configure(gapLabel(detail.layout), this.ghostBox.checked);
    this.drawGoalEditor(s);
    this.drawDisturb(s);
    const v = this.viewer;
    if (v) {
      v.world.add(s.model.group, s.ghost.group, s.marker.group, s.pick, s.pad.group, s.drop.group, s.trail.line, s.ghostTrail.line);
      v.animating = true;
      void Promise.all([s.model.meshes, s.ghost.meshes, s.marker.meshes]).then(() => v.invalidate());
    }
    return s;
  }

  private framed(s: Scene): () => THREE.Box3 {
    const v = this.viewer!;
    const marker = s.handles.kind === 'command' ? [] : [s.marker.group]; // a command is nowhere to frame
    return () => v.boxOf(...(s.rooted ? s.model.moving : [s.model.group]), ...(s.ghost.visible ? s.ghost.moving : []), ...marker);
  }

  private drawGoalEditor(s: Scene): void {
    const p = s.policy;
    const hkind = s.handles.kind;
    this.goalHint.textContent =
      hkind === 'ground'
        ? 'Drag the green goal on the ground in the view (or use the sliders): the policy heads for it.'
        : hkind === 'space'
          ? 'Drag the green goal in the view: it moves on a level plane at its height; the height slider raises or lowers it.'
          : hkind === 'command' && !p.goal_variables.length
            ? 'This policy takes no goal: it does its task from wherever it is (kick or push it below and watch it recover).'
            : hkind === 'command'
              ? 'Set the command with the slider: the policy follows it as it goes (push it below and watch it recover).'
            : 'Set the goal with the sliders: the green outline shows the pose it asks for.';
    this.goalEditor.textContent = '';
    s.inputs = p.goal_variables.map((name, i) => {
      const [lo, hi] = sliderRange(p.goal_low[i] ?? -1, p.goal_high[i] ?? 1, i === s.handles.heading);
      const v = s.goal[i] ?? 0;
      const value = h('span', { class: 'value' }, fmt(v));
      const label = i === s.handles.z ? `${name} (height)` : name;
      const slider = h('input', { type: 'range', min: lo, max: hi, step: (hi - lo) / 400, value: v, 'data-goal': name, 'aria-label': `goal ${name}` });
      const number = h('input', { type: 'number', step: 0.1, value: v.toFixed(2), 'data-goal-number': name, 'aria-label': `goal ${name} value` });
      slider.addEventListener('input', () => this.setGoalValue(i, Number(slider.value), slider));
      number.addEventListener('change', () => this.setGoalValue(i, Number(number.value), number));
      const range = h('span', { class: 'muted' }, ` trained ${fmt(p.goal_low[i])} … ${fmt(p.goal_high[i])}`);
      const row = h('div', { class: 'slider goal-row' }, h('div', { class: 'slider-head' }, h('b', {}, label), ' ', value, range), h('div', { class: 'goal-inputs' }, slider, number));
      this.goalEditor.append(row);
      return { slider, number, value, row };
    });
    this.showGoal(s);
  }

  private drawDisturb(s: Scene): void {
    this.disturb.textContent = '';
    const forces = s.detail.forces;
    this.disturb.append(
      h('div', { class: 'buttons' }, this.kickBtn),
      h(
        'p',
        { class: 'meaning' },
        'A kick jolts the velocities (up to a third of their trained range): the session goes on from the kicked state, with the same policy and goal, and the ghost with it.',
      ),
    );
    if (!forces.length) {
      this.disturb.append(h('p', { class: 'meaning', id: 'pd-no-forces' }, `${s.detail.model} has no force inputs, so there is no push: the kick stands in for one.`));
      return;
    }
    this.disturb.append(h('p', { class: 'meaning' }, 'Push: external forces, held while a slider is off zero.'));
    forces.forEach((f, i) => {
      const value = h('span', { class: 'value' }, '0');
      const range = h('input', { type: 'range', min: f.low, max: f.high, step: (f.high - f.low) / 200, value: 0, 'data-force': f.name, 'aria-label': `push ${f.name}` });
      range.addEventListener('input', () => {
        s.forces = [...s.forces];
        s.forces[i] = Number(range.value);
        value.textContent = fmt(s.forces[i]!);
        this.sendGoal(true);
      });
      this.disturb.append(h('div', { class: 'slider', title: f.description ?? '' }, h('div', { class: 'slider-head' }, h('b', {}, f.name), ' ', value, h('span', { class: 'muted' }, ` ${f.unit ?? ''}`)), range));
    });
  }

  private disposeScene(s: Scene): void {
    const v = this.viewer;
    if (v) {
      v.follow(null);
      v.animating = false;
    }
    s.model.dispose();
    s.ghost.dispose();
    s.marker.dispose();
    s.pick.geometry.dispose();
    (s.pick.material as THREE.Material).dispose();
    s.pick.removeFromParent();
    s.pad.dispose();
    s.drop.dispose();
    s.trail.dispose();
    s.ghostTrail.dispose();
    v?.invalidate();
  }

  /** Each frame: the goal to the session (while dragged, at most every GOAL_SEND_MS), the model and
   * its ghost where the session is (interpolated), the goal marker where the goal is, and the status. */
  private frame(now: number): void {
    const s = this.scene;
    const c = this.conn;
    if (!s || !c) return;
    this.sendGoal(!this.dragging);
    const poses = c.socket.sample(now);
    if (poses) {
      s.model.setPoses(poses);
      this.trace(s, poses, s.trail);
      const p = poses[0];
      if (p && s.rooted && this.viewer) s.drop.set(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0, this.viewer.groundZ);
    }
    const shadow = s.ghost.visible ? c.socket.sample(now, c.socket.shadow) : null;
    if (shadow) {
      s.ghost.setPoses(shadow);
      this.trace(s, shadow, s.ghostTrail);
    }
    s.ghostTrail.line.visible = s.ghost.visible;
    const at = this.point(s);
    if (at) {
      s.pick.position.set(...at);
      if (s.placed) s.marker.group.position.set(at[0] - s.placed[0], at[1] - s.placed[1], at[2] - s.placed[2]);
      if (this.viewer) s.pad.set(at[0], at[1], at[2], this.viewer.groundZ);
    }
    if (now - this.lastStatus > 200) {
      this.lastStatus = now;
      this.showStatus(s, c);
    }
  }

  private trace(s: Scene, poses: Pose[], t: Trail): void {
    const p = poses[s.rooted ? 0 : poses.length - 1];
    if (p) t.push(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0);
  }

  private showStatus(s: Scene, c: Conn): void {
    const last = c.socket.last;
    const d = this.status.dataset;
    if (!last) {
      this.status.textContent = `session ${c.info.id} · waiting for the first state…`;
      return;
    }
    const p = s.policy;
    d.t = String(last.t);
    d.state = JSON.stringify(last.state.map((v) => Number(v.toPrecision(4))));
    d.goal = JSON.stringify(last.goal ?? null);
    d.controls = JSON.stringify(last.controls ?? null);
    d.session = c.info.id;
    const controls = controlsLine(p.control_names, last.controls ?? []);
    const check = p.timed ? ` · its check ${timeToCheck(last.steps, c.goalStep, p.check_steps, s.detail.super_timestep) > 0 ? `in ${timeToCheck(last.steps, c.goalStep, p.check_steps, s.detail.super_timestep).toFixed(1)} s` : 'is past: it holds the goal'}` : '';
    this.status.textContent = `session ${c.info.id} · t = ${last.t.toFixed(1)} s · driven by ${p.name} (${p.version})${check} · controls: ${controls}`;
  }

  dispose(): void {
    this.alive = false;
    void this.stop();
    this.stops.forEach((f) => f());
    this.divergence.dispose();
    this.viewer?.dispose();
  }
}
