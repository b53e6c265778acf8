// A training as the "Add a model" panel shows it, folded from what the trainer service says: the reply
// to the upload, then its server-sent events (status, progress with new loss points, end), or a polled
// status. Pure functions: the panel draws what they return.
import type { TrainingAccepted, TrainingResult, TrainingStatus } from '../api/trainer';
import { fmt } from '../ui/dom';

export type TrainingState = TrainingStatus['status'];
export type TrainingPhase = TrainingStatus['phase'];

/** The running phases, in order (the trainer's PHASES). */
export const PHASES = ['validating', 'sampling', 'training', 'evaluating', 'exporting'] as const;
export const UPLOAD_SUFFIXES = ['.xml', '.zip', '.tar.gz', '.tgz'] as const;
const ENDED: readonly TrainingState[] = ['succeeded', 'failed', 'cancelled'];

export interface TrainingView {
  id: string;
  model: string;
  status: TrainingState;
  phase: TrainingPhase;
  percent: number;
  etaS: number | null;
  detail: string;
  attempt: number;
  /** The index in PHASES of the furthest phase reported (-1: none yet). */
  reached: number;
  /** The loss curve: [epoch, validation loss] by increasing epoch, one point per epoch. */
  losses: [number, number | null][];
  result: TrainingResult | null;
  error: string | null;
}

/** What the form asks for (text as typed; blanks are left to the service's defaults). */
export interface UploadForm {
  name: string;
  superStep: string;
  examples: string;
  epochs: string;
  hidden: string;
  rolloutSteps: string;
  entry: string;
  force: boolean;
  /** The operating spec, JSON as typed (docs/operating-spec.md); blank: none. */
  operatingSpec?: string;
}

/** Why a file cannot be uploaded, in words, or null when its type is one the trainer takes. */
export function uploadProblem(filename: string): string | null {
  const lower = filename.toLowerCase();
  if (UPLOAD_SUFFIXES.some((s) => lower.endsWith(s))) return null;
  return `${filename} is not a model the trainer takes: drop an MJCF file (.xml), or a .zip or .tar.gz of a model folder.`;
}

/** The multipart form's fields (TrainingOptions) for what was typed: blanks left out, super-step auto. */
export function formFields(f: UploadForm): Record<string, string> {
  const out: Record<string, string> = { super_step: f.superStep.trim() || 'auto' };
  const text: [string, string][] = [
    ['name', f.name],
    ['examples', f.examples],
    ['epochs', f.epochs],
    ['hidden', f.hidden],
    ['rollout_steps', f.rolloutSteps],
    ['entry', f.entry],
  ];
  for (const [k, v] of text) if (v.trim()) out[k] = v.trim();
  if (f.force) out.force = 'true';
  if (f.operatingSpec?.trim()) out.operating_spec = f.operatingSpec.trim();
  return out;
}

export function startView(a: TrainingAccepted): TrainingView {
  return { id: a.id, model: a.model, status: a.status, phase: a.phase, percent: 0, etaS: null, detail: a.message, attempt: 1, reached: -1, losses: [], result: null, error: null };
}

export function isEnded(v: TrainingView): boolean {
  return ENDED.includes(v.status);
}

/** New loss points merged into the curve: sorted by epoch, a repeated epoch keeps its latest loss. */
export function mergeLosses(curve: [number, number | null][], points: unknown): [number, number | null][] {
  if (!Array.isArray(points) || !points.length) return curve;
  const byEpoch = new Map(curve);
  for (const p of points) {
    if (Array.isArray(p) && typeof p[0] === 'number') byEpoch.set(p[0], typeof p[1] === 'number' ? p[1] : null);
  }
  return [...byEpoch.entries()].sort((a, b) => a[0] - b[0]);
}

const phaseIndex = (phase: string): number => (PHASES as readonly string[]).indexOf(phase);
const num = (v: unknown): number | null => (typeof v === 'number' && Number.isFinite(v) ? v : null);
const PHASE_OF_END: Record<string, TrainingPhase> = { succeeded: 'done', failed: 'failed', cancelled: 'cancelled' };

/** The view after one server-sent event (`status`, `progress`, `end`; others change nothing). An
 * attempt after a re-queue starts its progress and loss curve afresh. */
export function onEvent(v: TrainingView, event: string, data: Record<string, unknown>): TrainingView {
  if (isEnded(v)) return v;
  const attempt = num(data.attempt) ?? v.attempt;
  const base = attempt > v.attempt ? { ...v, attempt, percent: 0, etaS: null, reached: -1, losses: [] } : v;
  if (event === 'status' && (data.status === 'queued' || data.status === 'running')) {
    const requeued = data.status === 'queued' && typeof data.reason === 'string' ? `queued again: ${data.reason}` : null;
    return { ...base, status: data.status, phase: data.status === 'queued' ? 'queued' : base.phase === 'queued' ? 'validating' : base.phase, detail: requeued ?? base.detail };
  }
  if (event === 'progress') {
    const phase = typeof data.phase === 'string' && (PHASES as readonly string[]).includes(data.phase) ? (data.phase as TrainingPhase) : base.phase;
    return {
      ...base,
      status: 'running',
      phase,
      reached: Math.max(base.reached, phaseIndex(phase)),
      percent: Math.max(base.percent, Math.min(100, num(data.percent) ?? base.percent)),
      etaS: num(data.eta_s),
      detail: typeof data.detail === 'string' ? data.detail : base.detail,
      losses: mergeLosses(base.losses, data.losses),
    };
  }
  if (event === 'end') {
    const status = (typeof data.status === 'string' && ENDED.includes(data.status as TrainingState) ? data.status : 'failed') as TrainingState;
    const result = status === 'succeeded' && data.result && typeof data.result === 'object' ? (data.result as TrainingResult) : null;
    const reason = typeof data.reason === 'string' ? data.reason : null;
    return { ...base, status, phase: PHASE_OF_END[status]!, percent: status === 'succeeded' ? 100 : base.percent, etaS: null, result, error: status === 'succeeded' ? null : reason ?? `the training ${status}` };
  }
  return v;
}

/** The view from a polled status (the whole truth: it replaces what events said). */
export function fromStatus(v: TrainingView, s: TrainingStatus): TrainingView {
  return {
    ...v,
    status: s.status,
    phase: s.phase,
    percent: s.percent,
    etaS: s.eta_s ?? null,
    detail: s.detail ?? v.detail,
    attempt: Math.max(1, s.attempt ?? 1),
    reached: phaseIndex(s.phase) >= 0 ? phaseIndex(s.phase) : s.status === 'queued' ? -1 : v.reached,
    losses: mergeLosses([], (s.loss_curve ?? []).map((p) => [p.epoch, p.loss])),
    result: s.result ?? null,
    error: s.status === 'failed' || s.status === 'cancelled' ? s.error ?? `the training ${s.status}` : null,
  };
}

/** Time left in words: "about 2 min 10 s left"; empty when unknown. */
export function etaText(seconds: number | null): string {
  if (seconds === null || !Number.isFinite(seconds) || seconds < 0) return '';
  if (seconds < 5) return 'a few seconds left';
  const s = Math.round(seconds);
  if (s < 60) return `about ${s} s left`;
  const m = Math.floor(s / 60);
  if (m < 60) return `about ${m} min${s % 60 ? ` ${s % 60} s` : ''} left`;
  return `about ${Math.floor(m / 60)} h ${m % 60} min left`;
}

/** One line of where the training is, in words. */
export function statusLine(v: TrainingView): string {
  switch (v.status) {
    case 'queued':
      return `${v.model}: waiting for a training worker${v.detail.startsWith('queued again') ? ` (${v.detail})` : ''}.`;
    case 'running':
      return [`${v.model}: ${v.phase}`, v.detail && v.detail !== v.phase ? v.detail : '', `${Math.floor(v.percent)} %`, etaText(v.etaS)].filter(Boolean).join(' · ');
    case 'succeeded':
      return `${v.model} is trained: version ${v.result?.version ?? '?'}.`;
    case 'cancelled':
      return `The training of ${v.model} was cancelled; nothing was kept.`;
    default:
      return `The training of ${v.model} failed: ${v.error ?? 'no reason given'}`;
  }
}

export type StepState = 'done' | 'now' | 'todo' | 'stopped';

/** Each running phase and how far the training got with it (for the row of phases). */
export function phaseSteps(v: TrainingView): { phase: string; state: StepState }[] {
  return PHASES.map((phase, i) => {
    const state: StepState =
      v.status === 'succeeded' || i < v.reached ? 'done' : i > v.reached ? 'todo' : v.status === 'running' ? 'now' : 'stopped';
    return { phase, state };
  });
}

/** The result in rows of words: what was made, its one-step error against the linear baseline. */
export function resultRows(r: TrainingResult): [string, string][] {
  const rows: [string, string][] = [
    ['emulator', `${r.model}, version ${r.version}`],
    ['super-step n', String(r.substeps)],
    ['one-step error (1 − R²)', fmt(r.one_step_rel_error)],
    ['linear baseline', fmt(r.linear_baseline_rel_error)],
  ];
  const [e, l] = [r.one_step_rel_error, r.linear_baseline_rel_error];
  if (e !== null && l !== null && e > 0 && l > 0) rows.push(['against the linear baseline', e < l ? `${fmt(l / e)}× smaller error` : `${fmt(e / l)}× larger error`]);
  if (typeof r.examples === 'number') rows.push(['training examples', r.examples.toLocaleString('en')]);
  if (typeof r.weights === 'number') rows.push(['weights', r.weights.toLocaleString('en')]);
  const seconds = Object.entries(r.phase_seconds ?? {});
  if (seconds.length) rows.push(['time by phase', seconds.map(([k, s]) => `${k} ${fmt(s)} s`).join(', ')]);
  return rows;
}
