// Line plots in SVG: objective vs iteration, rollout error vs time. Pure helpers are exported for tests.
const SVG = 'http://www.w3.org/2000/svg';

export interface Series {
  name: string;
  xs: number[];
  ys: number[];
  color: string;
}

export interface PlotOptions {
  width?: number;
  height?: number;
  logY?: boolean;
  xLabel?: string;
  yLabel?: string;
}

/** About `count` round tick values covering [lo, hi]. */
export function niceTicks(lo: number, hi: number, count = 5): number[] {
  if (!Number.isFinite(lo) || !Number.isFinite(hi)) return [];
  if (hi <= lo) return [lo];
  const raw = (hi - lo) / Math.max(1, count);
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) ?? 10 * mag;
  const out: number[] = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Number(v.toPrecision(12)));
  return out;
}

/** [min, max] of the finite values (positive ones only when `positive`), or null if there are none. */
export function extent(values: number[], positive = false): [number, number] | null {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (!Number.isFinite(v) || (positive && v <= 0)) continue;
    lo = Math.min(lo, v);
    hi = Math.max(hi, v);
  }
  return lo <= hi ? [lo, hi] : null;
}

function el<K extends keyof SVGElementTagNameMap>(tag: K, attrs: Record<string, string | number>): SVGElementTagNameMap[K] {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  return e;
}

function label(v: number): string {
  const a = Math.abs(v);
  return a !== 0 && (a < 1e-2 || a >= 1e5) ? v.toExponential(0) : String(Number(v.toPrecision(3)));
}

export class LinePlot {
  readonly svg: SVGSVGElement;
  private series: Series[] = [];
  private readonly o: Required<PlotOptions>;

  constructor(opts: PlotOptions = {}) {
    this.o = { width: 520, height: 260, logY: false, xLabel: '', yLabel: '', ...opts };
    this.svg = el('svg', { viewBox: `0 0 ${this.o.width} ${this.o.height}`, class: 'plot', role: 'img' });
    this.render();
  }

  set(series: Series[]): void {
    this.series = series;
    this.render();
  }

  private render(): void {
    const { width: W, height: H, logY } = this.o;
    const m = { l: 56, r: 12, t: 12, b: 36 };
    this.svg.textContent = '';
    const xs = extent(this.series.flatMap((s) => s.xs));
    const ys = extent(this.series.flatMap((s) => s.ys), logY);
    this.svg.append(el('rect', { x: m.l, y: m.t, width: W - m.l - m.r, height: H - m.t - m.b, class: 'plot-bg' }));
    if (!xs || !ys) {
      const t = el('text', { x: W / 2, y: H / 2, 'text-anchor': 'middle', class: 'plot-empty' });
      t.textContent = 'no data yet';
      this.svg.append(t);
      return;
    }
    const f = (v: number): number => (logY ? Math.log10(v) : v);
    let [y0, y1] = [f(ys[0]), f(ys[1])];
    if (y1 - y0 < 1e-12) [y0, y1] = [y0 - (logY ? 0.5 : Math.abs(y0) * 0.1 + 1e-9), y1 + (logY ? 0.5 : Math.abs(y1) * 0.1 + 1e-9)];
    let [x0, x1] = xs;
    if (x1 <= x0) x1 = x0 + 1;
    const px = (x: number): number => m.l + ((x - x0) / (x1 - x0)) * (W - m.l - m.r);
    const py = (y: number): number => H - m.b - ((f(y) - y0) / (y1 - y0)) * (H - m.t - m.b);
    for (const x of niceTicks(x0, x1, 6)) {
      this.svg.append(el('line', { x1: px(x), x2: px(x), y1: H - m.b, y2: H - m.b + 4, class: 'plot-axis' }));
      const t = el('text', { x: px(x), y: H - m.b + 16, 'text-anchor': 'middle', class: 'plot-tick' });
      t.textContent = label(x);
      this.svg.append(t);
    }
    const yt = logY
      ? niceTicks(Math.floor(y0), Math.ceil(y1), 6).filter((e) => Number.isInteger(e) && e >= y0 - 1e-9 && e <= y1 + 1e-9).map((e) => 10 ** e)
      : niceTicks(y0, y1, 5);
    for (const y of yt) {
      this.svg.append(el('line', { x1: m.l, x2: W - m.r, y1: py(y), y2: py(y), class: 'plot-grid' }));
      const t = el('text', { x: m.l - 6, y: py(y) + 4, 'text-anchor': 'end', class: 'plot-tick' });
      t.textContent = label(y);
      this.svg.append(t);
    }
    if (this.o.xLabel) {
      const t = el('text', { x: (W + m.l) / 2, y: H - 4, 'text-anchor': 'middle', class: 'plot-label' });
      t.textContent = this.o.xLabel;
      this.svg.append(t);
    }
    if (this.o.yLabel) {
      const t = el('text', { x: 12, y: H / 2, 'text-anchor': 'middle', class: 'plot-label', transform: `rotate(-90 12 ${H / 2})` });
      t.textContent = this.o.yLabel;
      this.svg.append(t);
    }
    this.series.forEach((s, i) => {
      const pts: string[] = [];
      s.xs.forEach((x, j) => {
        const y = s.ys[j];
        if (y === undefined || !Number.isFinite(y) || (logY && y <= 0)) return;
        pts.push(`${px(x).toFixed(1)},${py(y).toFixed(1)}`);
      });
      this.svg.append(el('polyline', { points: pts.join(' '), fill: 'none', stroke: s.color, 'stroke-width': 2, 'data-series': s.name }));
      const lx = m.l + 48;
      const ly = m.t + 14 + i * 16;
      this.svg.append(el('line', { x1: lx - 40, x2: lx - 24, y1: ly - 4, y2: ly - 4, stroke: s.color, 'stroke-width': 2 }));
      const t = el('text', { x: lx - 20, y: ly, class: 'plot-legend' });
      t.textContent = s.name;
      this.svg.append(t);
    });
  }
}
