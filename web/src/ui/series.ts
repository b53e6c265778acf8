// Pure helpers for plots (no DOM, no plotting library): series on their own x values merged into the
// aligned columns a plot draws, values a logarithmic axis cannot show left out, legends' labels.

export interface Series {
  name: string;
  xs: number[];
  ys: number[];
  color: string;
  dash?: number[]; // a dashed line (e.g. a version the emulator does not serve)
}

/** The columns [x, y1, y2, …] over the union of every series' x values (sorted), with null where a
 * series has no value at an x, or a value that cannot be drawn (not finite; not positive on a log axis). */
export function aligned(series: Series[], logY = false): (number | null)[][] {
  const xs = [...new Set(series.flatMap((s) => s.xs.filter(Number.isFinite)))].sort((a, b) => a - b);
  const index = new Map(xs.map((x, i) => [x, i]));
  const cols: (number | null)[][] = [xs];
  for (const s of series) {
    const col: (number | null)[] = new Array<number | null>(xs.length).fill(null);
    s.xs.forEach((x, j) => {
      const i = index.get(x);
      const y = s.ys[j];
      if (i === undefined || y === undefined || y === null || !Number.isFinite(y) || (logY && y <= 0)) return;
      col[i] = y;
    });
    cols.push(col);
  }
  return cols;
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

/** A y range for a log axis that spans at least one decade, on whole decades. */
export function logRange(values: number[]): [number, number] | null {
  const e = extent(values, true);
  if (!e) return null;
  let lo = Math.floor(Math.log10(e[0]));
  let hi = Math.ceil(Math.log10(e[1]));
  if (hi <= lo) hi = lo + 1;
  return [10 ** lo, 10 ** hi];
}

/** A tick label for people: 3 significant digits; powers of ten as 1e-3 when tiny or huge; nothing
 * for a tick the plot leaves out (null). */
export function tickLabel(v: number | null): string {
  if (v === null || !Number.isFinite(v)) return '';
  if (v === 0) return '0';
  const a = Math.abs(v);
  if (a < 1e-3 || a >= 1e5) return v.toExponential(0).replace('e+', 'e');
  return String(Number(v.toPrecision(3)));
}

/** Whether v is a whole power of ten (1e-3, 0.1, 1, 100…). */
export function isDecade(v: number | null): boolean {
  if (v === null || !(v > 0)) return false;
  const e = Math.log10(v);
  return Math.abs(e - Math.round(e)) < 1e-9;
}

/** A round number (1, 2 or 5 × 10^k) at or above v; 1e-3 for a value that is not positive. */
export function roundUp(v: number | null): number {
  if (v === null || !(v > 0) || !Number.isFinite(v)) return 1e-3;
  const mag = 10 ** Math.floor(Math.log10(v));
  return ([1, 2, 5, 10].map((m) => m * mag).find((c) => c >= v * (1 - 1e-9)) ?? 10 * mag);
}
