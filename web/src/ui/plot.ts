// Line plots with uPlot (a small, fast, maintained canvas chart library: ~50 kB, no dependencies,
// built for time series that update live, which is what the dashboard plots: objective per iteration,
// rollout errors over time, divergence from MuJoCo over a session). A plot takes the width of its
// element and follows it; its legend sits below the curves, never over them.
import uPlot from 'uplot';
import 'uplot/dist/uPlot.min.css';
import { aligned, isDecade, logRange, roundUp, tickLabel, type Series } from './series';

export type { Series } from './series';

export interface PlotOptions {
  height?: number;
  logY?: boolean;
  xLabel?: string;
  yLabel?: string;
  /** a vertical line at this x (the replay's time), drawn when set */
  marker?: boolean;
  /** the series' names below the plot (default: yes) */
  legend?: boolean;
  /** a linear y axis from 0 to a round value above the data (errors, distances) */
  fromZero?: boolean;
  /** a dot at each point (a few measurements far apart) */
  points?: boolean;
  /** a fixed linear y range (a share in percent: [0, 100]) */
  yRange?: [number, number] | null;
}

const AXIS = { stroke: '#aab6c2', font: '12px system-ui, sans-serif', labelFont: '12px system-ui, sans-serif' };
const GRID = { stroke: '#2a323c', width: 1 };

export class LinePlot {
  readonly el: HTMLDivElement;
  private plot: uPlot | null = null;
  private series: Series[] = [];
  private signature = '';
  private markerX: number | null = null;
  private readonly o: Required<PlotOptions>;
  private readonly resize: ResizeObserver;
  private readonly empty: HTMLDivElement;

  constructor(opts: PlotOptions = {}) {
    this.o = { height: 220, logY: false, xLabel: '', yLabel: '', marker: false, legend: true, fromZero: false, points: false, yRange: null, ...opts };
    this.el = document.createElement('div');
    this.el.className = 'plot';
    this.el.setAttribute('role', 'img');
    this.empty = document.createElement('div');
    this.empty.className = 'plot-empty';
    this.empty.textContent = 'no data yet';
    this.empty.style.height = `${this.o.height}px`;
    this.el.append(this.empty);
    this.el.dataset.points = '0';
    this.resize = new ResizeObserver(() => {
      if (this.plot && this.el.clientWidth > 0) this.plot.setSize({ width: this.el.clientWidth, height: this.o.height });
      else if (!this.plot && this.series.length) this.draw();
    });
    this.resize.observe(this.el);
  }

  set(series: Series[]): void {
    this.series = series;
    this.el.dataset.points = String(Math.max(0, ...series.map((s) => s.xs.length)));
    this.el.dataset.series = JSON.stringify(series.map((s) => s.name));
    this.draw();
  }

  /** Move the vertical marker (the replay's clock) to x. */
  mark(x: number | null): void {
    this.markerX = x;
    this.plot?.redraw(false, false);
  }

  private draw(): void {
    const has = this.series.some((s) => s.xs.length > 0);
    this.empty.hidden = has;
    const width = this.el.clientWidth;
    if (!has || width <= 0) {
      if (!has) this.destroyPlot();
      return;
    }
    const data = aligned(this.series, this.o.logY) as uPlot.AlignedData;
    const signature = JSON.stringify(this.series.map((s) => [s.name, s.color, s.dash ?? null]));
    if (this.plot && signature === this.signature) {
      this.plot.setData(data);
      return;
    }
    this.destroyPlot();
    this.signature = signature;
    const logY = this.o.logY;
    // a log axis: lines and labels at whole decades only (not at 2…9 × 10^k)
    const decades = logY ? (_u: uPlot, splits: number[]): (number | null)[] => splits.map((v) => (isDecade(v) ? v : null)) : undefined;
    const opts: uPlot.Options = {
      width,
      height: this.o.height,
      legend: { show: this.o.legend, live: false },
      cursor: { drag: { x: false, y: false }, points: { show: false } },
      scales: {
        x: { time: false },
        // the data's range now (it grows as points arrive), on whole decades
        y: logY
          ? { distr: 3, log: 10, range: (_u, lo, hi) => (logRange([lo, hi]) ?? [1e-3, 1]) as uPlot.Range.MinMax }
          : this.o.yRange
            ? { range: [this.o.yRange[0], this.o.yRange[1]] as uPlot.Range.MinMax }
            : this.o.fromZero
            ? { range: (_u, _lo, hi) => [0, roundUp(hi)] as uPlot.Range.MinMax }
            : { auto: true },
      },
      axes: [
        { ...AXIS, label: this.o.xLabel, grid: GRID, ticks: GRID, values: (_u, v) => v.map(tickLabel) },
        {
          ...AXIS,
          label: this.o.yLabel,
          size: 60,
          space: 24, // px between labels: a short plot still gets three or more
          values: (_u, v) => v.map(tickLabel),
          ...(decades ? { filter: decades, grid: { ...GRID, filter: decades }, ticks: { ...GRID, filter: decades } } : { grid: GRID, ticks: GRID }),
        },
      ],
      series: [{}, ...this.series.map((s) => ({ label: s.name, stroke: s.color, width: 2, spanGaps: true, dash: s.dash, points: { show: this.o.points, size: 7 } }))],
      hooks: this.o.marker ? { draw: [(u: uPlot) => this.drawMarker(u)] } : {},
    };
    this.plot = new uPlot(opts, data, this.el);
  }

  private drawMarker(u: uPlot): void {
    if (this.markerX === null) return;
    const x = u.valToPos(this.markerX, 'x', true);
    const ctx = u.ctx;
    ctx.save();
    ctx.strokeStyle = '#ffffffaa';
    ctx.lineWidth = 1.5 * uPlot.pxRatio;
    ctx.beginPath();
    ctx.moveTo(x, u.bbox.top);
    ctx.lineTo(x, u.bbox.top + u.bbox.height);
    ctx.stroke();
    ctx.restore();
  }

  private destroyPlot(): void {
    this.plot?.destroy();
    this.plot = null;
    this.signature = '';
  }

  dispose(): void {
    this.resize.disconnect();
    this.destroyPlot();
    this.el.remove();
  }
}
