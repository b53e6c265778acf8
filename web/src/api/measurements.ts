// A model's evaluation (rollout error curves by super-step n, thesis Fig. 6.6) and benchmark (MuJoCo vs
// emulator, thesis Table 6.2), as the dashboard's server puts them together from each current version's
// eval.json and bench.json. Types come from proto/schemas/results (results.gen.ts).
// Either may be absent: null means "not measured".
import type { ModelBench, ModelEval, PhysicalErrorAt, PhysicalErrors, RolloutCurve } from './results.gen';

export type { ModelBench, ModelEval, RolloutCurve };
export type EvalResult = ModelEval;
export type BenchResult = ModelBench;

/** Rollout error curves by n (those with points), in increasing n, with the version each comes from. */
export function curvesOf(e: Pick<ModelEval, 'by_substeps'> | null): { substeps: number; version: string; curve: RolloutCurve }[] {
  if (!e) return [];
  return e.by_substeps
    .filter((r) => r.rollout_error_curve.t.length > 0)
    .map((r) => ({ substeps: r.substeps, version: r.version, curve: r.rollout_error_curve }))
    .sort((a, b) => a.substeps - b.substeps);
}

/** The name of an emulator by its super-step, saying when the emulator service does not serve it. */
export function servedLabel(substeps: number, served: boolean): string {
  return `N^${substeps}${served ? '' : ' (not loaded)'}`;
}

export type PhysicalQuantity = keyof PhysicalErrors;
export const PHYSICAL_QUANTITIES: Record<PhysicalQuantity, string> = {
  root_position_m: 'root position (m)',
  attitude_deg: 'attitude (°)',
  joint_angle_rad: 'joint angles (rad)',
  joint_position_m: 'slide joints (m)',
};

/** One table row per version (in increasing n) and per measured physical quantity. */
export function physicalRows(
  e: Pick<ModelEval, 'by_substeps'> | null,
): { substeps: number; version: string; quantity: PhysicalQuantity; values: PhysicalErrorAt[] }[] {
  if (!e) return [];
  const quantities = Object.keys(PHYSICAL_QUANTITIES) as PhysicalQuantity[];
  return [...e.by_substeps]
    .sort((a, b) => a.substeps - b.substeps)
    .flatMap((r) =>
      quantities
        .map((q) => ({ substeps: r.substeps, version: r.version, quantity: q, values: r.physical_errors?.[q] ?? [] }))
        .filter((row) => row.values.length > 0),
    );
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

/** The measurements the dashboard's server has for a model (`GET artifacts/{model}`: eval.json,
 * bench.json), so that only those are asked for: a model uploaded and trained has an evaluation but no
 * benchmark, and asking for what is not there puts a failed request in the console. null: the server
 * cannot say (it answers both then, as before). */
export async function measuredFiles(model: string): Promise<string[] | null> {
  const listed = await fetchOptional<{ measured?: unknown }>(`artifacts/${encodeURIComponent(model)}`);
  return listed && Array.isArray(listed.measured) ? listed.measured.filter((f): f is string => typeof f === 'string') : null;
}

export function loadEval(model: string, measured: string[] | null = null): Promise<ModelEval | null> {
  if (measured && !measured.includes('eval.json')) return Promise.resolve(null);
  return fetchOptional<ModelEval>(`artifacts/${encodeURIComponent(model)}/eval.json`);
}

export function loadBench(model: string, measured: string[] | null = null): Promise<ModelBench | null> {
  if (measured && !measured.includes('bench.json')) return Promise.resolve(null);
  return fetchOptional<ModelBench>(`artifacts/${encodeURIComponent(model)}/bench.json`);
}

/** When a rollout error curve first reaches `level` (linearly between its points), or null if it never
 * does within the curve. */
export function timeToReach(curve: RolloutCurve, level: number): number | null {
  const { t, error } = curve;
  for (let i = 0; i < t.length; i++) {
    const e = error[i];
    if (e === undefined || !Number.isFinite(e) || e < level) continue;
    if (i === 0) return t[0]!;
    const e0 = error[i - 1]!;
    const t0 = t[i - 1]!;
    return Number.isFinite(e0) && e > e0 ? t0 + ((level - e0) / (e - e0)) * (t[i]! - t0) : t[i]!;
  }
  return null;
}
