// A policy job as the Policies page shows it, folded from what the controller service says: the reply
// to POST /policies, then the job's server-sent events (`status`, one `progress` per training
// iteration, one `end`), or a polled status, and at the end its result. Pure functions: the page draws
// what they return.
import type { PolicyJobResult, PolicyJobStatus, PolicyManifest } from '../api/controller';
import { fmt } from '../ui/dom';

export type PolicyJobState = PolicyJobStatus['status'];
const ENDED: readonly PolicyJobState[] = ['succeeded', 'failed', 'cancelled'];

export interface PolicyTrainingView {
  id: string;
  task: string;
  status: PolicyJobState;
  attempt: number;
  iteration: number;
  /** The last batch's loss (null: none yet, or not finite). */
  loss: number | null;
  /** The share of the last MuJoCo check's runs that met the task (null before the first check). */
  successPhysics: number | null;
  mujocoSteps: number;
  elapsedS: number | null;
  /** The loss curve: [iteration, loss], by increasing iteration. */
  losses: [number, number | null][];
  /** The success share on MuJoCo at each check: [iteration, share], by increasing iteration. */
  successes: [number, number][];
  /** A suite task's (judged by its reward): the last check's mean return on MuJoCo, and at each check. */
  returnPhysics: number | null;
  returns: [number, number][];
  error: string | null;
  result: PolicyJobResult | null;
}

const num = (v: unknown): number | null => (typeof v === 'number' && Number.isFinite(v) ? v : null);

export function startPolicyView(id: string, task: string, status: PolicyJobState = 'queued'): PolicyTrainingView {
  return { id, task, status, attempt: 1, iteration: 0, loss: null, successPhysics: null, mujocoSteps: 0, elapsedS: null, losses: [], successes: [], returnPhysics: null, returns: [], error: null, result: null };
}

export function isPolicyEnded(v: PolicyTrainingView): boolean {
  return ENDED.includes(v.status);
}

/** A point added to a curve kept sorted by iteration; a repeated iteration keeps its latest value. */
function withPoint<T>(curve: [number, T][], x: number, y: T): [number, T][] {
  const out = curve.filter((p) => p[0] !== x);
  out.push([x, y]);
  return out.sort((a, b) => a[0] - b[0]);
}

/**
 * The view after one server-sent event (`status`, `progress`, `end`; others change nothing). A
 * progress event carries the success share of the *last* MuJoCo check at every iteration, so a new
 * check shows as a change of that share (or its first value) or as MuJoCo steps spent (a check runs
 * MuJoCo; so does refining the emulator, which may add a point the result's exact history drops):
 * that iteration gets a point on the success curve. An attempt after a re-queue starts its curves
 * afresh; an ended job stays ended.
 */
export function onPolicyEvent(v: PolicyTrainingView, event: string, data: Record<string, unknown>): PolicyTrainingView {
  if (isPolicyEnded(v)) return v;
  const attempt = num(data.attempt) ?? v.attempt;
  const base: PolicyTrainingView = attempt > v.attempt ? { ...startPolicyView(v.id, v.task, v.status), attempt } : v;
  if (event === 'status' && (data.status === 'queued' || data.status === 'running')) {
    const why = data.status === 'queued' && typeof data.reason === 'string' ? `queued again: ${data.reason}` : base.error;
    return { ...base, status: data.status, error: why };
  }
  if (event === 'progress') {
    const iteration = num(data.iteration);
    if (iteration === null) return base;
    const loss = num(data.loss);
    const success = num(data.success_physics);
    const steps = num(data.mujoco_steps) ?? 0;
    const checked = success !== null && (base.successPhysics === null || success !== base.successPhysics || steps > base.mujocoSteps);
    const ret = num(data.return_physics);
    const returned = ret !== null && (base.returnPhysics === null || ret !== base.returnPhysics || steps > base.mujocoSteps);
    return {
      ...base,
      status: 'running',
      iteration: Math.max(base.iteration, iteration),
      loss,
      successPhysics: success ?? base.successPhysics,
      mujocoSteps: Math.max(base.mujocoSteps, steps),
      elapsedS: num(data.elapsed_s) ?? base.elapsedS,
      losses: withPoint(base.losses, iteration, loss),
      successes: checked ? withPoint(base.successes, iteration, success) : base.successes,
      returnPhysics: ret ?? base.returnPhysics,
      returns: returned ? withPoint(base.returns, iteration, ret) : base.returns,
    };
  }
  if (event === 'end') {
    const status = (typeof data.status === 'string' && ENDED.includes(data.status as PolicyJobState) ? data.status : 'failed') as PolicyJobState;
    const reason = typeof data.reason === 'string' && data.reason ? data.reason : null;
    return { ...base, status, iteration: num(data.iterations) ?? base.iteration, error: status === 'succeeded' ? null : (reason ?? `the job ${status}`) };
  }
  return v;
}

/** The view from a polled status: its numbers and loss history replace what the events said (the
 * success curve stays: a status has only the last check's share). */
export function fromPolicyStatus(v: PolicyTrainingView, s: PolicyJobStatus): PolicyTrainingView {
  const restarted = (s.attempt ?? 1) > v.attempt;
  const history: [number, number | null][] = (s.loss_history ?? []).map((p) => [p.iteration, num(p.value)]);
  const success = num(s.success_physics);
  const successes = restarted ? [] : v.successes;
  const checked = success !== null && (restarted || success !== v.successPhysics) && (s.iteration ?? 0) > 0;
  const ret = num(s.return_physics);
  const returns = restarted ? [] : v.returns;
  const returned = ret !== null && (restarted || ret !== v.returnPhysics) && (s.iteration ?? 0) > 0;
  return {
    ...v,
    status: s.status,
    attempt: Math.max(v.attempt, s.attempt ?? 1),
    iteration: s.iteration ?? v.iteration,
    loss: num(s.loss),
    successPhysics: success,
    mujocoSteps: s.mujoco_steps ?? v.mujocoSteps,
    elapsedS: num(s.elapsed_s) ?? v.elapsedS,
    // the history is thinned to 100 points: keep the events' full curve while it is longer
    losses: history.length >= v.losses.length || restarted ? history : v.losses,
    successes: checked ? withPoint(successes, s.iteration ?? 0, success) : successes,
    returnPhysics: ret ?? (restarted ? null : v.returnPhysics),
    returns: returned ? withPoint(returns, s.iteration ?? 0, ret) : returns,
    error: s.status === 'failed' || s.status === 'cancelled' ? (s.error ?? `the job ${s.status}`) : null,
  };
}

/** The view with the job's result: its status, the histories the run kept (the success share at each
 * MuJoCo check, exactly), and the stored policy. */
export function withResult(v: PolicyTrainingView, r: PolicyJobResult): PolicyTrainingView {
  const successes = (r.success_history ?? []).flatMap((p): [number, number][] => (num(p.value) === null ? [] : [[p.iteration, p.value as number]]));
  const losses: [number, number | null][] = (r.loss_history ?? []).map((p) => [p.iteration, num(p.value)]);
  const returns = (r.return_history ?? []).flatMap((p): [number, number][] => (num(p.value) === null ? [] : [[p.iteration, p.value as number]]));
  return {
    ...v,
    status: r.status,
    iteration: r.iterations ?? v.iteration,
    successes: successes.length ? successes : v.successes,
    losses: losses.length >= v.losses.length ? losses : v.losses,
    successPhysics: successes.length ? successes[successes.length - 1]![1] : v.successPhysics,
    returns: returns.length ? returns : v.returns,
    returnPhysics: returns.length ? returns[returns.length - 1]![1] : v.returnPhysics,
    mujocoSteps: r.policy?.metrics?.mujoco_steps ?? v.mujocoSteps,
    error: r.status === 'succeeded' ? null : (r.reason ?? v.error ?? `the job ${r.status}`),
    result: r,
  };
}

/** A share (0..1) as a percentage for people: "75 %"; "–" when unknown. */
export function percent(v: number | null | undefined): string {
  return v === null || v === undefined || !Number.isFinite(v) ? '–' : `${Math.round(v * 100)} %`;
}

/** Seconds for people: "12.3 s", "2 min 5 s". */
export function seconds(v: number | null | undefined): string {
  if (v === null || v === undefined || !Number.isFinite(v)) return '–';
  if (v < 60) return `${v.toFixed(1)} s`;
  const s = Math.round(v);
  return `${Math.floor(s / 60)} min ${s % 60} s`;
}

/** One line of where the job is, in words. */
export function policyStatusLine(v: PolicyTrainingView): string {
  switch (v.status) {
    case 'queued':
      return `Job ${v.id} (${v.task}) is waiting for a controller worker${v.error ? ` (${v.error})` : ''}.`;
    case 'running':
      return v.iteration
        ? `Training ${v.task}: iteration ${v.iteration}, loss ${fmt(v.loss)}, success on MuJoCo ${percent(v.successPhysics)}, ${seconds(v.elapsedS)} in.`
        : `Training ${v.task}: drawing goals and starts on MuJoCo…`;
    case 'succeeded':
      return v.result?.policy ? `${v.task} is trained: policy version ${v.result.policy.version}.` : `Job ${v.id} ended after ${v.iteration} iterations.`;
    case 'cancelled':
      return v.result?.policy
        ? `Job ${v.id} was cancelled; the best policy so far was stored (version ${v.result.policy.version}).`
        : `Job ${v.id} was cancelled${v.result ? '; no policy was stored' : ''}.`;
    default:
      return `Job ${v.id} failed: ${v.error ?? 'no reason given'}`;
  }
}

/** The live numbers beside the curves: [label, value, key for data-* attributes]. */
export function progressRows(v: PolicyTrainingView): [string, string, string][] {
  return [
    ['iteration', String(v.iteration), 'iteration'],
    ['loss (last batch)', fmt(v.loss), 'loss'],
    v.returnPhysics !== null ? ['return on MuJoCo (last check)', fmt(v.returnPhysics), 'return'] : ['success on MuJoCo (last check)', percent(v.successPhysics), 'success'],
    ['MuJoCo steps', v.mujocoSteps.toLocaleString('en'), 'mujoco-steps'],
    ['elapsed', seconds(v.elapsedS), 'elapsed'],
  ];
}

/** How far a reward policy's emulator was to be trusted under it, and its falls on MuJoCo (rows only
 * for what the training measured). */
function trustRows(m: PolicyManifest['metrics']): [string, string][] {
  const rows: [string, string][] = [];
  if (typeof m?.outside_envelope === 'number') rows.push(["emulated states outside the emulator's envelope", percent(m.outside_envelope)]);
  if (typeof m?.root_drift_m === 'number') rows.push(["the emulator's root off MuJoCo's at 1 s", `${m.root_drift_m.toFixed(2)} m`]);
  const seeds = m?.seed_returns ?? [];
  if (seeds.length > 1) rows.push(['seeds trained side by side', `${seeds.length}, returns ${seeds.map((r) => r.toFixed(0)).join(', ')} (the best kept)`]);
  const falls = m?.falls ?? [];
  if (falls.length) {
    const first = falls.reduce((a, b) => (b.time_s < a.time_s ? b : a));
    const of = m?.evaluate_runs ? ` of ${m.evaluate_runs}` : '';
    // a body that crouched to the floor and stood again for the rest of the episode has fallen and
    // recovered: said apart
    const again = falls.filter((f) => typeof f.up_again_s === 'number').length;
    const recovered = again ? `; up again in ${again === falls.length ? 'all' : again}` : '';
    rows.push(['falls on MuJoCo', `${falls.length}${of} episodes (the first at ${seconds(first.time_s)}, episode ${first.episode}${recovered})`]);
  }
  return rows;
}

/** A stored policy's metrics in rows of words. */
export function metricsRows(p: PolicyManifest): [string, string][] {
  const m = p.metrics ?? {};
  const runs = m.evaluate_runs ? ` of ${m.evaluate_runs} held-out runs` : '';
  const episodes = m.evaluate_runs ? ` (mean of ${m.evaluate_runs} episodes)` : '';
  // a suite task's policy is judged by its reward's return, a goal-reaching one by its success share
  const judged: [string, string][] =
    typeof m.return_physics === 'number'
      ? [
          ['return on MuJoCo', `${fmt(m.return_physics)}${episodes}`],
          ['return on the emulator', `${fmt(m.return_emulator)}${episodes}`],
        ]
      : [
          ['success on MuJoCo', `${percent(m.success_physics)}${runs}`],
          ['success on the emulator', `${percent(m.success_emulator)}${runs}`],
        ];
  return [
    ['policy', `${p.name}, version ${p.version}`],
    ['emulator', `${p.model} ${p.emulator_version}`],
    ...judged,
    ['MuJoCo steps used', (m.mujoco_steps ?? 0).toLocaleString('en')],
    ['iterations', String(m.iterations ?? 0)],
    // (a service that counts them: how often the emulator was fine-tuned on the policy's MuJoCo runs)
    ...(typeof (m as { refinements?: unknown }).refinements === 'number' ? [['emulator refinements', String((m as { refinements: number }).refinements)] as [string, string]] : []),
    ...trustRows(m),
    ['training time', seconds(m.wall_s)],
    ['stopped by', m.stop === 'cancelled' ? 'a cancel (the best policy so far)' : (m.stop ?? 'budget')],
    ['goals', p.goal_variables.map((g, i) => `${g} ${fmt(p.goal_low[i])}…${fmt(p.goal_high[i])}`).join(', ') || 'none (the task has no parameters)'],
  ];
}

/** The controls a driven session last applied, for its status line: each by name when there are at
 *  most `shown`; past that (the runner's 29) their count and the `shown` largest in magnitude, so that
 *  the line stays one line and still says what the policy is pushing hardest. */
export function controlsLine(names: readonly string[], values: readonly number[], shown = 4): string {
  const named = values.map((u, i) => ({ name: names[i] ?? `u${i}`, u }));
  const text = (cs: typeof named) => cs.map((c) => `${c.name} ${fmt(c.u)}`).join(', ');
  if (named.length <= shown) return text(named);
  const largest = [...named].sort((a, b) => Math.abs(b.u) - Math.abs(a.u)).slice(0, shown);
  return `${named.length}, the largest ${text(largest)}`;
}
