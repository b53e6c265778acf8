// Beside a view that shows the emulator and MuJoCo together: how far apart they are, as numbers (now)
// and as a curve over time (the gap between the roots' positions, in metres).
import type { Gap } from '../scene/divergence';
import { fmt, h } from '../ui/dom';
import { LinePlot } from '../ui/plot';

export const GHOST_COLOR = 0x4dd0e1; // MuJoCo: a cyan outline
// the MuJoCo outline drawn over the emulated body, which it mostly covers: its faces barely there and
// its lines half see-through, so that the body under it keeps its own colours (at the usual 0.22 and
// 0.9 the lander's many small parts turned it cyan)
export const GHOST_LOOK = { ghost: true, color: GHOST_COLOR, opacity: 0.04, edgeOpacity: 0.5 } as const;
export const GOAL_COLOR = 0x7dffb0; // a goal: green
export const MODEL_TRAIL = 0xffb74d; // the emulated model's path: amber
const CAPACITY = 2400;

export class DivergencePanel {
  readonly el: HTMLElement;
  private readonly now: HTMLElement;
  private readonly plot: LinePlot;
  private readonly title: HTMLElement;
  private label = 'root position error';
  private ts: number[] = [];
  private gaps: number[] = [];
  private last = 0;

  /** `overlay`: drawn over a corner of the view it belongs to; else a block of its own. */
  constructor(id: string, opts: { marker?: boolean; overlay?: boolean } = {}) {
    this.now = h('p', { class: 'gap-now' });
    this.title = h('h3', {}, 'Emulator vs MuJoCo');
    // over the view it is a small corner readout (the model stays in sight); beside it, a full plot
    this.plot = new LinePlot({ height: opts.overlay ? 64 : 160, xLabel: opts.overlay ? '' : 'time (s)', marker: opts.marker ?? false, legend: false, fromZero: true });
    const cls = `card divergence${opts.overlay ? ' overlay' : ''}`;
    this.el = h('section', { class: cls, id, hidden: true }, this.title, this.now, this.plot.el);
  }

  /** What the position gap is for this model, and whether the panel shows. */
  configure(label: string, shown: boolean): void {
    this.label = label;
    this.title.textContent = `Emulator vs MuJoCo: ${label} (m)`;
    this.reset(shown);
  }

  reset(shown: boolean): void {
    this.ts = [];
    this.gaps = [];
    this.el.hidden = !shown;
    this.now.textContent = shown ? 'waiting for the first states of both…' : '';
    delete this.el.dataset.position;
    this.plot.set([]);
  }

  /** A live point: the gap at session time t (seconds). */
  add(t: number, gap: Gap): void {
    this.ts.push(t);
    this.gaps.push(gap.position);
    if (this.ts.length > CAPACITY) {
      this.ts.shift();
      this.gaps.shift();
    }
    // the number and the curve change a few times a second, not with every state: a readable number,
    // and each change of the page over the view is a repaint that the view's frame waits for
    const now = performance.now();
    if (now - this.last > 400 || this.ts.length < 3) {
      this.last = now;
      this.show(gap);
      this.draw();
    }
  }

  /** A whole run at once (a replay). */
  setAll(ts: number[], gaps: (Gap | null)[]): void {
    this.ts = [];
    this.gaps = [];
    ts.forEach((t, i) => {
      const g = gaps[i];
      if (!g) return;
      this.ts.push(t);
      this.gaps.push(g.position);
    });
    this.el.hidden = this.ts.length === 0;
    this.draw();
  }

  show(gap: Gap | null): void {
    if (!gap) return;
    this.el.dataset.position = gap.position.toFixed(4);
    this.now.textContent = `${this.label}: ${fmt(gap.position)} m · root attitude error: ${fmt(gap.attitude)}°`;
  }

  mark(t: number): void {
    this.plot.mark(t);
  }

  private draw(): void {
    this.plot.set([{ name: this.label, xs: this.ts, ys: this.gaps, color: '#4dd0e1' }]);
  }

  dispose(): void {
    this.plot.dispose();
    this.el.remove();
  }
}
