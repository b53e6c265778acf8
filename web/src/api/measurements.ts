// A model's evaluation (eval.json: rollout error curves, thesis Fig. 6.6) and benchmark (bench.json:
// MuJoCo vs emulator, thesis Table 6.2), served by the dashboard's server from artifacts/<model>/.
// Either may be absent: null means "not measured".

export interface Curve {
  t: number[];
  error: number[];
}

export interface EvalBySubsteps {
  substeps: number;
  rollout_error_curve?: Curve;
  one_step_rel_error?: number;
  rollout_error_at_20s?: number;
}

export interface EvalResult {
  substeps?: number;
  rollout_error_curve?: Curve;
  by_substeps?: EvalBySubsteps[];
  [key: string]: unknown;
}

export interface SingleRow {
  substeps: number;
  physics_s: number;
  emulator_s: number;
  ratio: number;
}

export interface BatchedRow {
  batch: number;
  physics_steps_per_s: number;
  emulator_steps_per_s: number;
  ratio: number;
}

export interface BenchResult {
  single?: SingleRow[];
  batched?: BatchedRow[];
  batched_substeps?: number;
}

/** Rollout error curves by n, from either the per-n list or the single top-level curve. */
export function curvesOf(e: EvalResult | null): { substeps: number; curve: Curve }[] {
  if (!e) return [];
  const rows = (e.by_substeps ?? [])
    .filter((r) => r.rollout_error_curve && r.rollout_error_curve.t.length > 0)
    .map((r) => ({ substeps: r.substeps, curve: r.rollout_error_curve as Curve }));
  if (rows.length) return rows.sort((a, b) => a.substeps - b.substeps);
  if (e.rollout_error_curve && e.rollout_error_curve.t.length > 0)
    return [{ substeps: e.substeps ?? 0, curve: e.rollout_error_curve }];
  return [];
}

async function fetchOptional<T>(url: string): Promise<T | null> {
  try {
    const r = await fetch(url, { cache: 'no-cache' });
    if (!r.ok) return null;
    return (await r.json()) as T;
  } catch {
    return null;
  }
}

export function loadEval(model: string): Promise<EvalResult | null> {
  return fetchOptional<EvalResult>(`artifacts/${encodeURIComponent(model)}/eval.json`);
}

export function loadBench(model: string): Promise<BenchResult | null> {
  return fetchOptional<BenchResult>(`artifacts/${encodeURIComponent(model)}/bench.json`);
}
