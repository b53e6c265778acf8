// Train a policy: the built-in policy tasks (GET /policy-tasks), a budget in seconds and whether to
// refine the emulator on the policy's own MuJoCo runs, "Train" (POST /policies); then the job live from
// its server-sent events (iteration, the loss curve, the success share on MuJoCo at each check, MuJoCo
// steps, elapsed time; a polled status behind them), "Cancel" (DELETE /policy-jobs/{id}), and once it
// ends the stored policy's metrics with "Drive it".
import type { PolicyManifest, PolicyTaskInfo } from '../api/controller';
import { errorText } from '../api/http';
import { fromPolicyStatus, isPolicyEnded, metricsRows, onPolicyEvent, policyStatusLine, progressRows, startPolicyView, withResult, type PolicyTrainingView } from '../policies/progress';
import { fmt, h } from '../ui/dom';
import { clearNotice, notify } from '../ui/notices';
import { LinePlot } from '../ui/plot';
import type { Ctx } from './context';

const POLL_MS = 1500;
const QUEUED_WARN_S = 8;
const DEFAULT_SECONDS = 60;

export class TrainPanel {
  readonly el: HTMLElement;
  private readonly tasksTable = h('table', { class: 'grid policy-tasks', id: 'pt-tasks' });
  private readonly criterion = h('p', { class: 'hint', id: 'pt-criterion' });
  private readonly seconds = h('input', { type: 'number', id: 'pt-seconds', min: 5, step: 1, value: DEFAULT_SECONDS, 'aria-label': 'training budget in seconds' });
  private readonly refine = h('input', { type: 'checkbox', id: 'pt-refine', checked: true });
  private readonly trainBtn = h('button', { id: 'pt-train', class: 'primary', disabled: true }, 'Train');
  private readonly cancelBtn = h('button', { id: 'pt-cancel', disabled: true }, 'Cancel');
  private readonly status = h('div', { class: 'status', id: 'pt-status' }, 'No job yet.');
  private readonly numbers = h('table', { class: 'facts', id: 'pt-progress' });
  private readonly loss = new LinePlot({ logY: true, xLabel: 'iteration', yLabel: 'loss', height: 180, legend: false });
  private readonly success = new LinePlot({ xLabel: 'iteration', yLabel: 'success (%)', height: 140, legend: false, yRange: [0, 100], points: true });
  private readonly returns = new LinePlot({ xLabel: 'iteration', yLabel: 'return', height: 140, legend: false, yRange: [0, 1000], points: true });
  private readonly successFigure: HTMLElement;
  private readonly returnFigure: HTMLElement;
  private readonly result = h('div', { class: 'result', id: 'pt-result', hidden: true });
  private tasks: PolicyTaskInfo[] = [];
  private task: string | null = null;
  private job: { view: PolicyTrainingView; events: EventSource | null; poll: number; queuedSince: number } | null = null;
  private alive = true;

  /** `drive(policy)`: "Drive it" on a stored policy. */
  constructor(
    private readonly ctx: Ctx,
    private readonly drive: (p: PolicyManifest) => void,
  ) {
    this.loss.el.id = 'pt-loss';
    this.success.el.id = 'pt-success';
    this.returns.el.id = 'pt-returns';
    this.successFigure = h('figure', { class: 'objective' }, h('figcaption', {}, 'Success on MuJoCo at each check'), this.success.el);
    // a suite task's policy is judged by the return of its episodes on MuJoCo (the suite's reward)
    this.returnFigure = h('figure', { class: 'objective', hidden: true }, h('figcaption', {}, 'Return on MuJoCo at each check (of 1,000)'), this.returns.el);
    this.el = h(
      'section',
      { class: 'card policy-train', id: 'policy-train' },
      h('h2', {}, 'Train a policy'),
      h(
        'p',
        { class: 'desc' },
        'A policy maps the state and a goal to the controls. It is trained by backpropagation through the emulator, checked on MuJoCo as it goes, and stored beside the emulator, ready to drive a session above.',
      ),
      h(
        'div',
        { class: 'cols' },
        h(
          'div',
          {},
          this.tasksTable,
          this.criterion,
          h(
            'div',
            { class: 'fields' },
            h('label', { class: 'field' }, 'Budget (seconds of training)', this.seconds),
            h('label', { class: 'check' }, this.refine, " Refine the emulator on the policy's own MuJoCo runs"),
          ),
          h('div', { class: 'buttons' }, this.trainBtn, this.cancelBtn),
          this.status,
        ),
        h(
          'div',
          {},
          this.numbers,
          h('figure', { class: 'objective' }, h('figcaption', {}, 'Loss per iteration (live)'), this.loss.el),
          this.successFigure,
          this.returnFigure,
          this.result,
        ),
      ),
    );
    this.trainBtn.addEventListener('click', () => void this.submit());
    this.cancelBtn.addEventListener('click', () => void this.cancel());
    this.showProgress();
  }

  async open(wanted: string | null): Promise<void> {
    try {
      this.tasks = await this.ctx.controller.policyTasks();
      if (!this.alive) return;
      this.drawTasks(wanted);
      clearNotice('policy-tasks');
    } catch (e) {
      this.criterion.textContent = 'No policy tasks: the controller service did not answer.';
      notify(`Cannot list the policy tasks. ${errorText(e)}`, 'error', 'policy-tasks');
    }
  }

  private drawTasks(wanted: string | null): void {
    const goal = (t: PolicyTaskInfo): string =>
      (t.goal_variables ?? []).map((g, i) => `${g} ${fmt(t.goal_low?.[i])}…${fmt(t.goal_high?.[i])}`).join(', ') || '–';
    this.tasksTable.textContent = '';
    this.tasksTable.append(h('tr', {}, h('th', {}, ''), h('th', {}, 'task'), h('th', {}, 'model'), h('th', {}, 'goal (trained range)')));
    for (const t of this.tasks) {
      const radio = h('input', { type: 'radio', name: 'pt-task', value: t.name, 'data-task': t.name, 'aria-label': t.name });
      radio.addEventListener('change', () => this.choose(t.name));
      this.tasksTable.append(
        h('tr', { 'data-task': t.name }, h('td', {}, radio), h('td', {}, h('b', {}, t.name)), h('td', {}, t.model), h('td', {}, goal(t))),
        h('tr', { class: 'task-desc' }, h('td', {}), h('td', { colspan: 3, class: 'meaning' }, t.description ?? '')),
      );
    }
    const pick = this.tasks.find((t) => t.name === wanted) ?? this.tasks[0];
    if (pick) this.choose(pick.name);
    else this.criterion.textContent = 'The controller service offers no policy tasks.';
  }

  private choose(name: string): void {
    this.task = name;
    const t = this.tasks.find((x) => x.name === name);
    this.tasksTable.querySelectorAll<HTMLInputElement>('input[name="pt-task"]').forEach((r) => (r.checked = r.value === name));
    this.tasksTable.querySelectorAll<HTMLElement>('tr[data-task]').forEach((r) => r.classList.toggle('chosen', r.dataset.task === name));
    this.criterion.textContent = t?.success_criterion ? `Success: ${t.success_criterion}.` : '';
    const reward = t?.kind === 'reward';
    this.successFigure.hidden = reward;
    this.returnFigure.hidden = !reward;
    this.trainBtn.disabled = !t || (this.job !== null && !isPolicyEnded(this.job.view));
  }

  // ---------------------------------------------------------------- the job
  private async submit(): Promise<void> {
    const task = this.task;
    if (!task) return;
    const budget = Number(this.seconds.value);
    if (!Number.isFinite(budget) || budget < 5) {
      notify(`The budget must be at least 5 seconds (got ${this.seconds.value || 'nothing'}).`, 'error', 'policy-job');
      return;
    }
    this.stopFollowing();
    this.result.hidden = true;
    this.result.textContent = '';
    this.trainBtn.disabled = true;
    this.status.textContent = 'Submitting…';
    clearNotice('policy-job');
    try {
      const accepted = await this.ctx.controller.submitPolicy({
        task,
        seconds: budget,
        refine: this.refine.checked,
        idempotency_key: `dash-${Date.now().toString(36)}-${Math.random().toString(36).slice(2, 10)}`,
      });
      if (!this.alive) return;
      const job = { view: startPolicyView(accepted.id, task, accepted.status), events: null as EventSource | null, poll: 0, queuedSince: performance.now() };
      this.job = job;
      this.status.dataset.job = accepted.id;
      this.cancelBtn.disabled = false;
      this.update();
      const es = this.ctx.controller.policyEvents(accepted.id);
      job.events = es;
      for (const event of ['status', 'progress', 'end']) {
        es.addEventListener(event, (ev) => {
          if (this.job !== job) return;
          job.view = onPolicyEvent(job.view, event, JSON.parse((ev as MessageEvent<string>).data) as Record<string, unknown>);
          if (event === 'end') {
            es.close();
            void this.poll();
          }
          this.update();
        });
      }
      es.onerror = () => {
        if (es.readyState === EventSource.CLOSED) job.events = null;
      };
      job.poll = window.setInterval(() => void this.poll(), POLL_MS);
    } catch (e) {
      this.status.textContent = 'The job was not submitted.';
      notify(`Could not submit the policy job. ${errorText(e)}`, 'error', 'policy-job');
      this.trainBtn.disabled = false;
    }
  }

  private async cancel(): Promise<void> {
    const job = this.job;
    if (!job) return;
    this.cancelBtn.disabled = true;
    try {
      await this.ctx.controller.cancelPolicy(job.view.id);
      this.status.textContent = `Cancelling job ${job.view.id}: it stops at its next iteration and keeps the best policy so far…`;
    } catch (e) {
      notify(`Could not cancel the job. ${errorText(e)}`, 'error', 'policy-job');
      this.cancelBtn.disabled = isPolicyEnded(job.view);
    }
  }

  private async poll(): Promise<void> {
    const job = this.job;
    if (!job) return;
    try {
      const st = await this.ctx.controller.policyJob(job.view.id);
      clearNotice('policy-job-lost');
      if (this.job !== job) return;
      job.view = fromPolicyStatus(job.view, st);
      if (st.status === 'queued') {
        const waited = (performance.now() - job.queuedSince) / 1000;
        if (waited > QUEUED_WARN_S)
          notify(
            `Policy job ${job.view.id} has waited ${waited.toFixed(0)} s and no controller worker has started it. Is a worker running? ` +
              '(make up starts one; by hand: python -m services.controller.worker)',
            'warning',
            'policy-job-queued',
          );
      } else {
        job.queuedSince = performance.now();
        clearNotice('policy-job-queued');
      }
      this.update();
      if (isPolicyEnded(job.view)) await this.finish();
    } catch (e) {
      notify(`Lost contact with the controller service while following policy job ${job.view.id}. ${errorText(e)}`, 'error', 'policy-job-lost');
    }
  }

  private async finish(): Promise<void> {
    const job = this.job;
    if (!job) return;
    this.stopFollowing();
    try {
      const r = await this.ctx.controller.policyResult(job.view.id);
      if (this.job !== job || !this.alive) return;
      job.view = withResult(job.view, r);
      this.update();
      if (job.view.status === 'failed') notify(`The policy job failed: ${job.view.error ?? 'no reason was given'}.`, 'error', 'policy-job');
      if (r.policy) this.showResult(r.policy);
    } catch (e) {
      notify(`The policy job ended but its result could not be read. ${errorText(e)}`, 'error', 'policy-job');
    }
  }

  private showResult(p: PolicyManifest): void {
    const driveBtn = h('button', { id: 'pt-drive', class: 'primary' }, 'Drive it');
    driveBtn.addEventListener('click', () => this.drive(p));
    this.result.textContent = '';
    this.result.dataset.successPhysics = String(p.metrics?.success_physics ?? '');
    this.result.dataset.policy = `${p.model}/${p.name}/${p.version}`;
    this.result.append(
      h('h3', {}, 'The stored policy'),
      h('table', { class: 'facts', id: 'pt-metrics' }, ...metricsRows(p).map(([k, v]) => h('tr', {}, h('th', {}, k), h('td', {}, v)))),
      h('div', { class: 'buttons' }, driveBtn),
    );
    this.result.hidden = false;
  }

  private stopFollowing(): void {
    const job = this.job;
    if (!job) return;
    job.events?.close();
    job.events = null;
    window.clearInterval(job.poll);
    clearNotice('policy-job-queued');
  }

  private update(): void {
    const job = this.job;
    if (!job) return;
    const v = job.view;
    this.status.textContent = policyStatusLine(v);
    this.status.dataset.status = v.status;
    this.cancelBtn.disabled = isPolicyEnded(v);
    this.trainBtn.disabled = !isPolicyEnded(v) || !this.task;
    this.showProgress();
  }

  private showProgress(): void {
    const v = this.job?.view ?? startPolicyView('', '');
    this.numbers.textContent = '';
    this.numbers.append(...progressRows(v).map(([k, val, key]) => h('tr', { 'data-key': key }, h('th', {}, k), h('td', {}, val))));
    this.numbers.dataset.iteration = String(v.iteration);
    this.numbers.dataset.successPhysics = String(v.successPhysics ?? '');
    this.numbers.dataset.mujocoSteps = String(v.mujocoSteps);
    this.loss.set(v.losses.length ? [{ name: 'loss', xs: v.losses.map((p) => p[0]), ys: v.losses.map((p) => p[1] ?? NaN), color: '#4fc3f7' }] : []);
    this.success.set(v.successes.length ? [{ name: 'success on MuJoCo', xs: v.successes.map((p) => p[0]), ys: v.successes.map((p) => 100 * p[1]), color: '#aed581' }] : []);
    this.loss.el.dataset.losses = String(v.losses.length);
    this.success.el.dataset.checks = String(v.successes.length);
    this.returns.set(v.returns.length ? [{ name: 'return on MuJoCo', xs: v.returns.map((p) => p[0]), ys: v.returns.map((p) => p[1]), color: '#aed581' }] : []);
    this.returns.el.dataset.checks = String(v.returns.length);
  }

  dispose(): void {
    this.alive = false;
    this.stopFollowing();
    this.loss.dispose();
    this.success.dispose();
    this.returns.dispose();
  }
}
