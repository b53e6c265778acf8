// Replaying a controller: the emulated and the physical (MuJoCo) trajectories side by side, each with
// the translucent goal, interpolated between super-steps at the display rate.
import type { ModelGeometry } from '../api/emulator.gen';
import type { EmulatorApi } from '../api/emulator';
import type { JobResult } from '../api/controller';
import { locate, lerpPoses, type Pose } from '../scene/interp';
import { ModelView } from '../scene/model';
import { makeViewer, staging } from '../scene/setup';
import type { Viewer } from '../scene/viewer';
import { fmt, h } from '../ui/dom';

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

function verdict(err: number | null | undefined, ok: boolean | null | undefined): string {
  const mark = ok === true ? 'reached the goal' : ok === false ? 'missed the goal' : '';
  return `final error ${fmt(err)}${mark ? ` (${mark})` : ''}`;
}

export class Replay {
  readonly el: HTMLElement;
  private readonly views: { viewer: Viewer; model: ModelView; poses: Pose[][] }[] = [];
  private times: number[] = [];
  private t = 0;
  private playing = true;
  private last = 0;
  private readonly slider: HTMLInputElement;
  private readonly clock: HTMLElement;
  private readonly playBtn: HTMLButtonElement;
  private stops: (() => void)[] = [];

  constructor(
    private readonly api: EmulatorApi,
    private readonly geometry: ModelGeometry,
    private readonly result: JobResult,
    private readonly superTimestep: number,
  ) {
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
    const target = r.target_state && r.target_state.every((v) => v !== null) ? (r.target_state as number[]) : null;
    const [pe, pp, pt] = await Promise.all([
      emulated.length ? this.api.poses(model, emulated, r.version ?? undefined) : null,
      physical.length ? this.api.poses(model, physical, r.version ?? undefined) : null,
      target ? this.api.poses(model, [target], r.version ?? undefined) : null,
    ]);
    const n = Math.max(emulated.length, physical.length);
    const times = r.times && r.times.length === n ? r.times : Array.from({ length: n }, (_, i) => i * this.superTimestep);
    this.times = times;
    const row = h('div', { class: 'replay-views' });
    this.el.append(
      h(
        'p',
        { class: 'final-errors', id: 'final-errors' },
        h('b', {}, 'Emulator: '),
        verdict(r.final_error_emulator, r.success_emulator),
        ' · ',
        h('b', {}, 'MuJoCo: '),
        verdict(r.final_error_physics, r.success_physics),
      ),
      row,
      h('div', { class: 'replay-bar' }, this.playBtn, this.slider, this.clock),
    );
    const sides: [string, Pose[][] | undefined][] = [
      ['Emulator', pe?.poses],
      ['MuJoCo (physics)', pp?.poses],
    ];
    for (const [title, poses] of sides) {
      const host = h('div', { class: 'view replay-view', 'data-side': title });
      row.append(h('div', { class: 'replay-side' }, h('h3', {}, title), host));
      if (!poses?.length) {
        host.append(h('p', { class: 'muted' }, 'No trajectory.'));
        continue;
      }
      const viewer = makeViewer(host);
      if (!viewer) continue;
      const view = new ModelView(this.geometry);
      viewer.world.add(view.group);
      if (pt) {
        const goal = new ModelView(this.geometry, { ghost: true, color: 0x7dffb0, opacity: 0.5 });
        goal.setPoses(pt.poses[0] ?? []);
        viewer.world.add(goal.group);
      }
      const all = poses.flat();
      const st = staging(this.geometry, poses[0] ?? this.geometry.rest_poses);
      const xs = all.map((p) => p[0] ?? 0);
      const ys = all.map((p) => p[1] ?? 0);
      const zs = all.map((p) => p[2] ?? 0);
      const mid = [(Math.min(...xs) + Math.max(...xs)) / 2, (Math.min(...ys) + Math.max(...ys)) / 2, (Math.min(...zs) + Math.max(...zs)) / 2];
      const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), Math.max(...zs) - Math.min(...zs));
      viewer.setGroundHeight(st.ground);
      viewer.frame(mid, Math.max(st.radius, span * 0.45));
      this.views.push({ viewer, model: view, poses });
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
    for (const v of this.views) {
      const a = v.poses[Math.min(i, v.poses.length - 1)];
      const b = v.poses[Math.min(i + 1, v.poses.length - 1)];
      if (a && b) v.model.setPoses(lerpPoses(a, b, f));
    }
    this.clock.textContent = `${this.t.toFixed(1)} / ${this.end.toFixed(1)} s`;
    this.el.dataset.t = this.t.toFixed(2);
  }

  dispose(): void {
    for (const s of this.stops) s();
    for (const v of this.views) {
      v.model.dispose();
      v.viewer.dispose();
    }
    this.views.length = 0;
    this.el.remove();
  }
}
