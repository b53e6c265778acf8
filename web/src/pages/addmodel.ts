// "Add a model" on the Models page: drop (or choose) an MJCF or a .zip / .tar.gz of a model folder, name
// it, pick its super-step and sample budget, and the trainer service checks it at once (a refusal is
// shown in its own words: which file is missing, which actuator has no ctrlrange, ...), then trains it.
// Its progress comes live from the training's server-sent events (phase, percent, time left, the loss
// curve); once done, the result (one-step error against the linear baseline, errors in physical units)
// and "Drive it", which opens the Playground on the new emulator as soon as the emulator service has it.
// An optional operating spec (JSON: where the model operates, docs/operating-spec.md) goes with the upload;
// the trainer's refusal of it (an actuator the model does not have, ...) is shown beside its box.
import SPEC_DOC from '../../../docs/operating-spec.md?raw';
import type { EmulatorApi } from '../api/emulator';
import { errorText, ServiceError } from '../api/http';
import type { TrainerApi } from '../api/trainer';
import { PHYSICAL_QUANTITIES, type PhysicalQuantity } from '../api/measurements';
import { driveHash } from '../session/start';
import { SPEC_PLACEHOLDER, specProblem, specRefused } from '../training/operating';
import { formFields, fromStatus, isEnded, onEvent, phaseSteps, resultRows, startView, statusLine, uploadProblem, type TrainingView } from '../training/progress';
import { fmt, h, physicalText } from '../ui/dom';
import { notify } from '../ui/notices';
import { LinePlot } from '../ui/plot';

const POLL_MS = 4000; // a status poll beside the events (a proxy may hold events back)
const SERVED_WAIT_MS = 60000;

/** A labelled input of the form. */
function field(label: string, input: HTMLElement, hint: string): HTMLElement {
  return h('label', { class: 'field' }, h('span', {}, label), input, h('small', { class: 'hint' }, hint));
}

/** The result's errors in physical units: mean / 90th percentile at each time of the rollouts. */
function physicalTable(v: TrainingView): HTMLElement | null {
  const errors = v.result?.physical_errors;
  if (!errors) return null;
  const rows = (Object.keys(PHYSICAL_QUANTITIES) as PhysicalQuantity[]).filter((q) => errors[q]?.length);
  if (!rows.length) return null;
  const times = [...new Set(rows.flatMap((q) => errors[q]!.map((p) => p.t_s)))].sort((a, b) => a - b);
  const table = h(
    'table',
    { class: 'grid physical', id: 'am-physical' },
    h('tr', {}, h('th', {}, 'quantity'), ...times.map((t) => h('th', { class: 'num' }, `${fmt(t)} s`))),
    ...rows.map((q) =>
      h(
        'tr',
        { 'data-quantity': q },
        h('td', {}, PHYSICAL_QUANTITIES[q]),
        ...times.map((t) => {
          const p = errors[q]!.find((x) => x.t_s === t);
          return h('td', { class: 'num' }, p ? `${physicalText(p.mean)} / ${physicalText(p.p90)}` : '–');
        }),
      ),
    ),
  );
  return h('div', {}, h('p', { class: 'hint' }, 'Rollouts against MuJoCo, in physical units: mean / 90th percentile over the trials'), table);
}

/** The panel; `trained(model)` is called once a new emulator is served (the page lists it). */
export function addModelPanel(trainer: TrainerApi | null, emulator: EmulatorApi, trained: (model: string) => void): { el: HTMLElement; dispose: () => void } {
  const el = h('section', { class: 'card add-model', id: 'add-model' }, h('h2', {}, 'Add a model'));
  if (!trainer) {
    el.append(h('p', { class: 'muted' }, 'This deployment has no trainer service (TRAINER_URL is empty): models are added on the server with neuro train --mjcf.'));
    return { el, dispose: () => undefined };
  }
  const file = h('input', { type: 'file', id: 'am-file', accept: '.xml,.zip,.tar.gz,.tgz', hidden: true });
  const chosen = h('span', { class: 'chosen', id: 'am-chosen' }, 'Drop an MJCF (.xml) or a .zip / .tar.gz of a model folder here, or choose a file');
  const drop = h('label', { class: 'drop', id: 'am-drop', for: 'am-file' }, chosen, file);
  const name = h('input', { type: 'text', id: 'am-name', placeholder: 'from the MJCF', pattern: '[A-Za-z0-9][A-Za-z0-9._-]*', maxlength: 64 });
  const superStep = h('input', { type: 'text', id: 'am-super-step', value: 'auto', size: 6 });
  const examples = h('input', { type: 'number', id: 'am-examples', min: 100, max: 1000000, step: 100, placeholder: 'default' });
  const epochs = h('input', { type: 'number', id: 'am-epochs', min: 1, max: 5000, placeholder: 'default' });
  const hidden = h('input', { type: 'text', id: 'am-hidden', placeholder: 'e.g. 64,64', size: 10 });
  const rollout = h('input', { type: 'number', id: 'am-rollout-steps', min: 0, max: 64, placeholder: 'default' });
  const entry = h('input', { type: 'text', id: 'am-entry', placeholder: 'the only one', size: 14 });
  const force = h('input', { type: 'checkbox', id: 'am-force' });
  const spec = h('textarea', { id: 'am-spec', rows: 5, spellcheck: false, placeholder: SPEC_PLACEHOLDER, 'aria-describedby': 'am-spec-hint am-spec-error' });
  const specError = h('div', { class: 'refusal', id: 'am-spec-error', role: 'alert', hidden: true });
  const specDoc = URL.createObjectURL(new Blob([SPEC_DOC], { type: 'text/plain;charset=utf-8' })); // the format, offline
  const specField = h(
    'div',
    { class: 'field spec' },
    h('label', { for: 'am-spec' }, 'Operating spec'),
    spec,
    h(
      'small',
      { class: 'hint', id: 'am-spec-hint' },
      "Optional: where the model operates, as JSON (its keyframe, the controls' centres and spreads, how runs start). Empty: its keyframes, else the controls that hold it still. ",
      h('a', { href: specDoc, target: '_blank', rel: 'noopener', id: 'am-spec-doc' }, 'The format: docs/operating-spec.md'),
    ),
    specError,
  );
  const submit = h('button', { id: 'am-submit', class: 'primary', disabled: true }, 'Upload and train');
  const cancel = h('button', { id: 'am-cancel', hidden: true }, 'Cancel the training');
  const problem = h('div', { class: 'refusal', id: 'am-error', role: 'alert', hidden: true });
  const steps = h('ol', { class: 'phases', id: 'am-phases' });
  const bar = h('progress', { id: 'am-percent', max: 100, value: 0 });
  const line = h('p', { class: 'status', id: 'am-status' }, 'What happens: the model is checked at once, then sampled in MuJoCo, learnt, and evaluated against MuJoCo; the emulator service then serves it.');
  const loss = new LinePlot({ logY: true, xLabel: 'epoch', yLabel: 'validation loss', height: 170, legend: false });
  loss.el.id = 'am-loss';
  const result = h('div', { class: 'result', id: 'am-result', hidden: true });
  el.append(
    h('p', { class: 'desc' }, 'Any MuJoCo model becomes an emulator: its includes, meshes and textures come along in the folder or archive. Bad files are refused with the reason, before anything is trained.'),
    h(
      'div',
      { class: 'cols' },
      h(
        'div',
        { class: 'am-form' },
        drop,
        h('div', { class: 'fields' }, field('Name', name, 'in the registry'), field('Super-step', superStep, 'n physical steps, or auto'), field('Sample budget', examples, 'training examples')),
        specField,
        h(
          'details',
          { class: 'more' },
          h('summary', {}, 'More options'),
          h('div', { class: 'fields' }, field('Epochs', epochs, 'at most'), field('Hidden layers', hidden, 'widths'), field('Rollout steps', rollout, '0: off'), field('Entry XML', entry, 'in an archive')),
          h('label', { class: 'check' }, force, ' keep the emulator even if it misses the accuracy bar'),
        ),
        h('div', { class: 'buttons' }, submit, cancel),
        problem,
      ),
      h('div', { class: 'am-progress', id: 'am-progress' }, steps, bar, line, h('figure', { class: 'loss' }, h('figcaption', {}, 'Loss curve: validation loss after each epoch'), loss.el), result),
    ),
  );

  let picked: File | null = null;
  let current: TrainingView | null = null;
  let events: EventSource | null = null;
  let poll = 0;
  let alive = true;

  const pick = (f: File | null): void => {
    problem.hidden = true;
    picked = null;
    submit.disabled = true;
    if (!f) return;
    const why = uploadProblem(f.name);
    chosen.textContent = `${f.name} (${(f.size / 1024).toFixed(1)} kB)`;
    if (why) return refuse(why);
    picked = f;
    submit.disabled = !!current && !isEnded(current);
  };
  const refuse = (text: string): void => {
    problem.textContent = text;
    problem.hidden = false;
  };
  /** The operating spec's problem beside its box (null: none). */
  const specSays = (text: string | null): void => {
    specError.textContent = text ?? '';
    specError.hidden = text === null;
    spec.setAttribute('aria-invalid', String(text !== null));
  };
  spec.addEventListener('input', () => specSays(null));
  const stopFollowing = (): void => {
    events?.close();
    events = null;
    window.clearInterval(poll);
  };

  const draw = (v: TrainingView): void => {
    steps.replaceChildren(...phaseSteps(v).map((s) => h('li', { class: `step ${s.state}`, 'data-phase': s.phase, 'data-state': s.state }, s.phase)));
    bar.value = v.percent;
    line.textContent = statusLine(v);
    Object.assign(line.dataset, { status: v.status, phase: v.phase, percent: String(Math.floor(v.percent)), training: v.id });
    loss.set([{ name: 'validation loss', xs: v.losses.map((p) => p[0]), ys: v.losses.map((p) => p[1] ?? NaN), color: '#4fc3f7' }]);
    cancel.hidden = isEnded(v);
    submit.disabled = !picked || !isEnded(v);
    if (v.status === 'failed' || v.status === 'cancelled') refuse(statusLine(v));
  };

  /** The result, and "Drive it" once the emulator service serves the new version. */
  const finish = async (v: TrainingView): Promise<void> => {
    const r = v.result;
    if (!r) return;
    const drive = h('button', { id: 'am-drive', class: 'primary', disabled: true }, 'Waiting for the emulator service to load it…');
    drive.addEventListener('click', () => (location.hash = driveHash(r.model)));
    const notes = (r.notes ?? []).map((n) => h('li', {}, n));
    result.replaceChildren(
      h('div', { class: 'buttons' }, drive),
      h('h3', {}, 'Result'),
      h('table', { class: 'facts', id: 'am-facts' }, ...resultRows(r).map(([k, val]) => h('tr', {}, h('th', {}, k), h('td', {}, val)))),
      physicalTable(v) ?? h('p', { class: 'muted' }, 'No errors in physical units (not measured).'),
      notes.length ? h('ul', { class: 'notes' }, ...notes) : '',
    );
    result.hidden = false;
    const t0 = performance.now();
    while (alive && performance.now() - t0 < SERVED_WAIT_MS) {
      try {
        const { models } = await emulator.models();
        const m = models.find((x) => x.model === r.model);
        if (m && (m.version === r.version || m.versions.includes(r.version))) {
          drive.disabled = false;
          drive.textContent = 'Drive it';
          trained(r.model);
          return;
        }
      } catch {
        /* the emulator service did not answer: the health line says so; try again */
      }
      await new Promise((ok) => window.setTimeout(ok, 1000));
    }
    if (alive) drive.textContent = 'The emulator service has not loaded it yet: reload the page later';
  };

  const update = (next: TrainingView): void => {
    if (!alive || !current || next.id !== current.id) return;
    const ended = !isEnded(current) && isEnded(next);
    current = next;
    draw(next);
    if (!ended) return;
    stopFollowing();
    // the whole truth once more (the events' end carries the result as the worker wrote it)
    const settle = async (): Promise<void> => {
      try {
        const st = await trainer.training(next.id);
        if (current?.id === st.id) current = fromStatus(current, st);
      } catch {
        /* the end event's result stands */
      }
      if (!alive || !current) return;
      draw(current);
      await finish(current);
    };
    void settle();
  };

  const follow = (v: TrainingView): void => {
    const es = trainer.events(v.id);
    events = es;
    for (const type of ['status', 'progress', 'end']) {
      es.addEventListener(type, (ev) => {
        if (current) update(onEvent(current, type, JSON.parse((ev as MessageEvent<string>).data) as Record<string, unknown>));
      });
    }
    poll = window.setInterval(() => {
      trainer
        .training(v.id)
        .then((st) => {
          if (current && current.id === st.id && !isEnded(current)) update(fromStatus(current, st));
        })
        .catch(() => undefined); // the events carry on; the next poll tries again
    }, POLL_MS);
  };

  const upload = async (): Promise<void> => {
    if (!picked) return;
    const sent = spec.value;
    const bad = specProblem(sent);
    specSays(bad);
    if (bad) return;
    stopFollowing();
    problem.hidden = true;
    result.hidden = true;
    submit.disabled = true;
    line.textContent = `Uploading ${picked.name} and checking it…`;
    const form = { name: name.value, superStep: superStep.value, examples: examples.value, epochs: epochs.value, hidden: hidden.value, rolloutSteps: rollout.value, entry: entry.value, force: force.checked, operatingSpec: sent };
    try {
      const accepted = await trainer.upload(picked, picked.name, formFields(form));
      if (!alive) return;
      current = startView(accepted);
      draw(current);
      line.textContent = accepted.message;
      follow(current);
    } catch (e) {
      submit.disabled = false;
      line.textContent = 'Nothing was uploaded.';
      // the service's own words say what is wrong with the model (or with the operating spec, shown beside
      // its box); anything else goes to the notices too
      if (e instanceof ServiceError && e.detail && e.status !== null && e.status < 500 && specRefused(e.code, sent)) specSays(`The operating spec was refused: ${e.detail}`);
      else if (e instanceof ServiceError && e.detail && e.status !== null && e.status < 500) refuse(`This model cannot be trained: ${e.detail}`);
      else {
        refuse(errorText(e));
        notify(`Could not upload the model. ${errorText(e)}`, 'error', 'add-model');
      }
    }
  };

  file.addEventListener('change', () => pick(file.files?.[0] ?? null));
  drop.addEventListener('dragover', (ev) => {
    ev.preventDefault();
    drop.classList.add('over');
  });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (ev) => {
    ev.preventDefault();
    drop.classList.remove('over');
    pick(ev.dataTransfer?.files[0] ?? null);
  });
  submit.addEventListener('click', () => void upload());
  cancel.addEventListener('click', () => {
    if (current) trainer.cancel(current.id).catch((e: unknown) => notify(`Could not cancel the training. ${errorText(e)}`, 'error', 'add-model'));
  });
  return {
    el,
    dispose: () => {
      alive = false;
      stopFollowing();
      loss.dispose();
      URL.revokeObjectURL(specDoc);
    },
  };
}
