// A controller's outcome, as the controller service decided it: one success criterion (the job's
// checks on the final state, in the service's own words), and for the emulator and for MuJoCo whether
// each check held and the value it measured. Nothing here judges success again: the verdicts are the
// result's `success_emulator`, `success_physics` and `checks_*[i].passed`.
import type { JobResult } from '../api/controller';
import { hasGoalState } from '../session/target';
import { fmt, h } from '../ui/dom';

type Verdict = boolean | null | undefined;

/** A side's verdict in words. */
export function verdictText(ok: Verdict): string {
  return ok === true ? 'meets the criterion' : ok === false ? 'misses the criterion' : 'has no criterion to meet';
}

type Summarised = Pick<JobResult, 'success_emulator' | 'success_physics' | 'success_criterion'> &
  Partial<Pick<JobResult, 'verdict' | 'final_error_physics' | 'final_error_emulator' | 'objective' | 'objective_physics' | 'spec'>>;

/** The job's verdict as the service words it ("succeeded" only when the controller meets the criterion
 * on MuJoCo; "done, no criterion" when the task states none), or the same worked out for a service
 * that does not send it. */
export function verdictOf(r: Summarised): string {
  if (r.verdict) return r.verdict;
  // no verdict on either side: no criterion (whose text then says so: "no success criterion")
  if (r.success_physics == null && r.success_emulator == null) return 'done, no criterion';
  return r.success_physics === true ? 'succeeded' : r.success_emulator === true ? 'done, criterion met on the emulator only' : 'done, criterion missed';
}

/** How far the controller ends from its goal (or, without a goal state, its objective), on MuJoCo and on
 * the emulator: without a criterion this number is the only measure of what the controller did. */
function endError(r: Summarised): string {
  if (r.spec && !hasGoalState(r.spec.state_weights)) return `its objective is ${fmt(r.objective_physics)} on MuJoCo (${fmt(r.objective)} on the emulator)`;
  if (r.final_error_physics === undefined && r.final_error_emulator === undefined) return '';
  return `its final error to the target is ${fmt(r.final_error_physics)} on MuJoCo (${fmt(r.final_error_emulator)} on the emulator)`;
}

/** One line on a finished job: its verdict and where its controller meets the criterion. A run that
 * ended normally is not called a success when there was no criterion to meet. */
export function outcomeSummary(r: Summarised): string {
  if (verdictOf(r) === 'done, no criterion') {
    const err = endError(r);
    return `Done, no criterion: the task states no success criterion${err ? `; ${err}` : ''}.`;
  }
  const e = r.success_emulator;
  const p = r.success_physics;
  if (p === true && e === true) return 'The controller meets the success criterion on MuJoCo and on the emulator.';
  if (p === true) return 'The controller meets the success criterion on MuJoCo (not on the emulator).';
  if (e === true) return 'The controller meets the success criterion on the emulator but misses it on MuJoCo.';
  return 'The controller misses the success criterion on the emulator and on MuJoCo.';
}

function mark(ok: Verdict): HTMLElement {
  return h('span', { class: ok === true ? 'pass' : ok === false ? 'fail' : 'muted' }, ok === true ? '✓' : ok === false ? '✗' : '–');
}

/** The criterion and its checks on both sides: a table with one row per check. */
export function outcomeView(r: JobResult): HTMLElement {
  const emu = r.checks_emulator ?? [];
  const phys = r.checks_physics ?? [];
  const rows = Math.max(emu.length, phys.length);
  const cell = (c: (typeof emu)[number] | undefined): HTMLElement =>
    h('td', { 'data-passed': c ? String(c.passed) : '' }, c ? mark(c.passed) : '–', ' ', c ? fmt(c.value) : '');
  const attrs = {
    class: 'outcome',
    id: 'outcome',
    'data-success-emulator': String(r.success_emulator ?? ''),
    'data-success-physics': String(r.success_physics ?? ''),
    'data-verdict': verdictOf(r),
  };
  return h(
    'div',
    attrs,
    h('p', { class: 'verdict', id: 'verdict' }, h('b', {}, 'Verdict: '), verdictOf(r)),
    h('p', { class: 'criterion' }, h('b', {}, 'Success criterion: '), r.success_criterion ?? 'none stated by the task'),
    rows
      ? h(
          'table',
          { class: 'grid checks' },
          h('tr', {}, h('th', {}, 'check at the end'), h('th', {}, 'emulator'), h('th', {}, 'MuJoCo')),
          ...Array.from({ length: rows }, (_, i) => h('tr', { class: 'check-row' }, h('td', {}, (phys[i] ?? emu[i])!.check), cell(emu[i]), cell(phys[i]))),
          h(
            'tr',
            { class: 'verdict' },
            h('th', {}, 'all checks'),
            h('td', { 'data-side': 'emulator' }, mark(r.success_emulator), ' ', verdictText(r.success_emulator)),
            h('td', { 'data-side': 'physics' }, mark(r.success_physics), ' ', verdictText(r.success_physics)),
          ),
        )
      : null,
    hasGoalState(r.spec?.state_weights)
      ? h(
          'p',
          { class: 'muted final-errors', id: 'final-errors' },
          `Weighted distance of the final state to the target (what the objective penalises, not the criterion): emulator ${fmt(r.final_error_emulator)}, MuJoCo ${fmt(r.final_error_physics)}.`,
        )
      : h(
          'p',
          { class: 'muted final-errors', id: 'final-errors' },
          `No goal state: the objective (lower is better) is emulator ${fmt(r.objective)}, MuJoCo ${fmt(r.objective_physics)}.`,
        ),
    r.bptt_networks === 'global'
      ? h('p', { class: 'muted', id: 'bptt-networks' }, "Gradients went through the hierarchy's global network alone: the objective depends only on its parts' frames.")
      : null,
  );
}
