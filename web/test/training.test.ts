import { describe, expect, it } from 'vitest';
import type { TrainingAccepted, TrainingStatus } from '../src/api/trainer';
import { driveHash, driveNow } from '../src/session/start';
import { etaText, formFields, fromStatus, isEnded, mergeLosses, onEvent, phaseSteps, resultRows, startView, statusLine, uploadProblem, type TrainingView } from '../src/training/progress';

const ACCEPTED: TrainingAccepted = { id: 't1', status: 'queued', phase: 'queued', model: 'tinybot', new_version: false, message: 'tinybot: 1 degrees of freedom, 1 controls; queued to train a new model' };
const RESULT = { model: 'tinybot', version: 'n10-1', artifact: 'tinybot/n10-1', substeps: 10, one_step_rel_error: 0.02, linear_baseline_rel_error: 0.1, examples: 200, weights: 250, phase_seconds: { sampling: 1.5, training: 2 } };

/** Events as the trainer service sends them for one training. */
function run(events: [string, Record<string, unknown>][]): TrainingView {
  return events.reduce((v, [e, d]) => onEvent(v, e, d), startView(ACCEPTED));
}

describe('a training, from its events', () => {
  it('follows the phases, percent, time left and loss curve to its result', () => {
    const v = run([
      ['status', { status: 'running', attempt: 1 }],
      ['progress', { phase: 'validating', percent: 1, detail: 'reading the model', eta_s: null, attempt: 1, losses: [] }],
      ['progress', { phase: 'sampling', percent: 20, detail: 'sampling: 1,000 of 4,200 examples', eta_s: 80, attempt: 1, losses: [] }],
      ['progress', { phase: 'training', percent: 50, detail: 'epoch 2 of at most 3', eta_s: 20, attempt: 1, losses: [[1, 0.5], [2, 0.3]] }],
    ]);
    expect([v.status, v.phase, v.percent, v.etaS]).toEqual(['running', 'training', 50, 20]);
    expect(v.losses).toEqual([
      [1, 0.5],
      [2, 0.3],
    ]);
    expect(statusLine(v)).toBe('tinybot: training · epoch 2 of at most 3 · 50 % · about 20 s left');
    expect(phaseSteps(v).map((s) => s.state)).toEqual(['done', 'done', 'now', 'todo', 'todo']);
    const done = onEvent(onEvent(v, 'progress', { phase: 'training', percent: 60, losses: [[3, 0.2]] }), 'end', { status: 'succeeded', phase: 'done', reason: null, result: RESULT });
    expect([done.status, done.phase, done.percent, done.result?.version, done.error]).toEqual(['succeeded', 'done', 100, 'n10-1', null]);
    expect(done.losses.map((p) => p[0])).toEqual([1, 2, 3]);
    expect(isEnded(done) && phaseSteps(done).every((s) => s.state === 'done')).toBe(true);
    expect(statusLine(done)).toBe('tinybot is trained: version n10-1.');
    expect(onEvent(done, 'progress', { phase: 'sampling', percent: 3 })).toBe(done); // an ended training stays ended
  });

  it('says where a failed training stopped, and why', () => {
    const v = run([
      ['progress', { phase: 'validating', percent: 1 }],
      ['end', { status: 'failed', phase: 'failed', reason: "model wobbly diverged 0.05 s into a run at joint 'spring'" }],
    ]);
    expect(phaseSteps(v).map((s) => s.state)).toEqual(['stopped', 'todo', 'todo', 'todo', 'todo']);
    expect(statusLine(v)).toBe("The training of tinybot failed: model wobbly diverged 0.05 s into a run at joint 'spring'");
  });

  it('starts a re-queued attempt afresh and keeps one point per epoch', () => {
    const first = run([['progress', { phase: 'training', percent: 40, attempt: 1, losses: [[1, 0.5], [2, 0.4]] }]]);
    const again = onEvent(first, 'status', { status: 'queued', attempt: 2, reason: 'its worker stopped' });
    expect([again.phase, again.percent, again.losses, again.reached]).toEqual(['queued', 0, [], -1]);
    expect(statusLine(again)).toBe('tinybot: waiting for a training worker (queued again: its worker stopped).');
    expect(mergeLosses([[1, 0.5]], [[1, 0.45], [3, null], 'x'])).toEqual([
      [1, 0.45],
      [3, null],
    ]);
  });

  it('takes a polled status as the whole truth', () => {
    const st: TrainingStatus = { id: 't1', status: 'running', phase: 'evaluating', model: 'tinybot', super_step: 10, examples: 200, percent: 88, eta_s: 4, detail: 'rollouts', loss_curve: [{ epoch: 1, loss: 0.3 }], created_at: 0, attempt: 1 };
    const v = fromStatus(startView(ACCEPTED), st);
    expect([v.phase, v.reached, v.losses, statusLine(v)]).toEqual(['evaluating', 3, [[1, 0.3]], 'tinybot: evaluating · rollouts · 88 % · a few seconds left']);
    const gone = fromStatus(v, { ...st, status: 'cancelled', phase: 'cancelled', error: null });
    expect([gone.error, gone.reached, statusLine(gone)]).toEqual(['the training cancelled', 3, 'The training of tinybot was cancelled; nothing was kept.']);
  });
});

describe('the upload form', () => {
  it('takes MJCF files and archives only, saying what it takes', () => {
    expect(['robot.XML', 'bot.zip', 'bot.tar.gz', 'bot.tgz'].map(uploadProblem)).toEqual([null, null, null, null]);
    expect(uploadProblem('robot.urdf')).toMatch(/robot\.urdf is not a model the trainer takes: drop an MJCF file \(\.xml\)/);
  });

  it('sends what was typed, blanks left to the service, super-step auto by default', () => {
    const blank = { name: ' ', superStep: '', examples: '', epochs: '', hidden: '', rolloutSteps: '', entry: '', force: false };
    expect(formFields(blank)).toEqual({ super_step: 'auto' });
    expect(formFields({ ...blank, name: 'bot ', superStep: '10', examples: '200', rolloutSteps: '0', force: true })).toEqual({ super_step: '10', name: 'bot', examples: '200', rollout_steps: '0', force: 'true' });
  });
});

describe('words and numbers', () => {
  it('says the time left in words', () => {
    expect([null, 3, 42, 130, 7260].map(etaText)).toEqual(['', 'a few seconds left', 'about 42 s left', 'about 2 min 10 s left', 'about 2 h 1 min left']);
  });

  it('lists the result with its error against the linear baseline', () => {
    const rows = Object.fromEntries(resultRows(RESULT));
    expect(rows['one-step error (1 − R²)']).toBe('0.02');
    expect(rows['against the linear baseline']).toBe('5× smaller error');
    expect(rows['time by phase']).toBe('sampling 1.5 s, training 2 s');
  });

  it('opens the Playground on a model, driving it at once', () => {
    const hash = driveHash('my bot');
    expect(hash).toBe('#/playground?model=my+bot&start=rest&drive=1');
    const query = hash.split('?')[1]!;
    expect([new URLSearchParams(query).get('model'), driveNow(query), driveNow('model=x')]).toEqual(['my bot', true, false]);
  });
});
