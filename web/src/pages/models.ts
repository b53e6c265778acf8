// Models: "Add a model" (addmodel.ts: upload a MuJoCo model and train it), then every loaded emulator
// with its manifest (layout, controls, δt and n), training metrics, the rollout error over time (thesis
// Fig. 6.6) with what its numbers mean, the errors in physical units (metres, degrees, radians) and the
// speed table (thesis Table 6.2) when measured. The page stays short enough to read down: the curves and
// rows are those of the versions the emulator service serves (the others are named in one line), long
// state layouts and the speed tables are folded, and only the measurements the server lists are fetched.
import type { ModelDetail } from '../api/emulator.gen';
import { controlMeaning } from '../session/inputs';
import { errorText } from '../api/http';
import {
  curvesOf,
  loadBench,
  loadEval,
  measuredFiles,
  PHYSICAL_QUANTITIES,
  physicalRows,
  servedLabel,
  timeToReach,
  type BenchResult,
  type EvalResult,
} from '../api/measurements';
import { fmt, h, physicalText } from '../ui/dom';
import { notify } from '../ui/notices';
import { LinePlot } from '../ui/plot';
import { addModelPanel } from './addmodel';
import type { Page } from './context';

const COLORS = ['#4fc3f7', '#ffb74d', '#aed581', '#f06292', '#ba68c8'];
const METRICS: [string, string][] = [
  ['one_step_rel_error', 'one-step relative error'],
  ['validation_rel_error', 'validation relative error'],
  ['linear_baseline_rel_error', 'linear baseline error'],
  ['weights', 'weights'],
  ['examples', 'training examples'],
  ['total_seconds', 'training time (s)'],
];

function facts(m: ModelDetail): HTMLElement {
  const rows: [string, string][] = [
    ['version', m.version],
    ['state size', String(m.state_size)],
    ['physics δt, super-step Δt = n·δt', `${fmt(m.timestep)} s, ${fmt(m.super_timestep)} s (n = ${m.substeps})`],
    ['versions loaded', m.versions.join(', ')],
  ];
  return h('table', { class: 'facts' }, ...rows.map(([k, v]) => h('tr', {}, h('th', {}, k), h('td', {}, v))));
}

function inputs(m: ModelDetail): HTMLElement {
  const rows = [
    // what 1 applies in short (its sign convention, often a sentence, when pointed at): a row per line
    ...m.controls.map((c) => ['control', c.name, `${fmt(c.low)} … ${fmt(c.high)}`, controlMeaning(c, false), controlMeaning(c)]),
    ...m.forces.map((f) => ['force', f.name, `${fmt(f.low)} … ${fmt(f.high)}`, f.unit ?? '', f.description ?? '']),
  ];
  if (!rows.length) return h('p', { class: 'muted' }, 'No inputs: a passive model.');
  return folded(
    rows.length,
    `${m.controls.length} controls${m.forces.length ? ` and ${m.forces.length} forces` : ''}: show them`,
    h(
      'table',
      { class: 'grid inputs' },
      h('tr', {}, h('th', {}, 'input'), h('th', {}, 'name'), h('th', {}, 'trained range'), h('th', {}, 'what 1 applies')),
      ...rows.map(([kind, name, range, short, long]) => h('tr', { title: long ?? '' }, ...[kind, name, range, short].map((v) => h('td', {}, v ?? '')))),
    ),
  );
}

// a table longer than this is folded (the dolphin's state layout, the runner's joint targets): it is
// reference, not news, and unfolded it makes the page many screens long
const ROWS_SHOWN = 12;

function folded(rows: number, summary: string, table: HTMLElement): HTMLElement {
  return rows <= ROWS_SHOWN ? table : h('details', { class: 'more folded' }, h('summary', {}, summary), table);
}

function layout(m: ModelDetail): HTMLElement {
  const table = h(
    'table',
    { class: 'grid' },
    h('tr', {}, h('th', {}, 'state group'), h('th', {}, 'kind'), h('th', {}, 'values')),
    ...m.layout.map((g) => h('tr', {}, h('td', {}, g.name), h('td', {}, g.kind), h('td', {}, `[${g.offset}:${g.offset + g.size}] ${(g.labels ?? []).join(' ')}`))),
  );
  return folded(m.layout.length, `${m.layout.length} state groups, ${m.state_size} values: show them`, table);
}

function metrics(m: ModelDetail): HTMLElement {
  const got = METRICS.filter(([k]) => typeof m.metrics?.[k] === 'number');
  if (!got.length) return h('p', { class: 'muted' }, 'No training metrics in the manifest.');
  // two measures a row: six one-number rows made every card a screen taller
  const pairs = got.map(([k, label]) => [h('th', {}, label), h('td', {}, fmt(m.metrics?.[k] as number))]);
  const rows = Array.from({ length: Math.ceil(pairs.length / 2) }, (_, i) => h('tr', {}, ...pairs[2 * i]!, ...(pairs[2 * i + 1] ?? [])));
  return h('table', { class: 'facts metrics' }, ...rows);
}

/** The curves to draw: those of the versions the emulator service serves (all of them when it serves
 * none of the measured ones), and the others, named in a line instead of drawn. */
function splitServed<T extends { version: string }>(m: ModelDetail, rows: T[]): { shown: T[]; others: T[] } {
  const served = rows.filter((r) => m.versions.includes(r.version));
  const shown = served.length ? served : rows;
  return { shown, others: rows.filter((r) => !shown.includes(r)) };
}

function rolloutPlot(m: ModelDetail, e: EvalResult | null, plots: LinePlot[]): HTMLElement {
  const { shown: curves, others } = splitServed(m, curvesOf(e));
  if (!curves.length) return h('p', { class: 'muted not-measured' }, 'Rollout error: not measured. ', h('code', {}, `neuro eval ${m.model} --json`), ' measures it.');
  const plot = new LinePlot({
    logY: true,
    xLabel: 'time (s)',
    yLabel: 'normalised error',
    height: 180,
    legend: curves.length > 1, // one curve is named in the sentence below it
  });
  plots.push(plot);
  const series = curves.map((c, i) => {
    const served = m.versions.includes(c.version);
    return {
      name: servedLabel(c.substeps, served),
      xs: c.curve.t,
      ys: c.curve.error,
      color: COLORS[i % COLORS.length]!,
      dash: served ? undefined : [6, 4],
    };
  });
  const figure = h(
    'figure',
    { class: 'rollout' },
    h('figcaption', {}, 'Rollout error against MuJoCo over time, by super-step n (thesis Fig. 6.6)'),
    plot.el,
    errorMeaning(m, curves.find((c) => c.version === m.version) ?? curves[0]!),
    others.length
      ? h(
          'p',
          { class: 'muted also-measured' },
          `Also measured: ${others.map((c) => `N^${c.substeps}`).join(', ')}, versions the emulator service has not loaded (it loads each model's latest).`,
        )
      : null,
  );
  // drawn once the figure is in the page (the plot takes its element's width)
  queueMicrotask(() => plot.set(series));
  return figure;
}

/** What the rollout error's numbers mean, in words, and when this emulator's error gets there. */
function errorMeaning(m: ModelDetail, c: { substeps: number; curve: EvalResult['rollout_error_curve'] }): HTMLElement {
  const close = timeToReach(c.curve, 0.1);
  const apart = timeToReach(c.curve, 1);
  const end = c.curve.t[c.curve.t.length - 1] ?? 0;
  const here =
    `Here N^${c.substeps} ` +
    (close === null ? `stays within 0.1 for all ${fmt(end)} s measured` : close <= 0 ? 'starts above 0.1' : `stays within 0.1 for ${fmt(close)} s`) +
    (apart === null ? '' : ` and has decorrelated (about 1) after ${fmt(apart)} s`) +
    '.';
  return h(
    'p',
    {
      class: 'error-meaning',
      id: `meaning-${m.model}`,
      title:
        "The normalised error is each state variable's distance from MuJoCo's divided by how much that variable varies over typical states, averaged over the variables and the trials.",
    },
    h('b', {}, 'Normalised error: '),
    "below 0.1 the emulator follows MuJoCo closely. About 1 means the emulated state is as far from MuJoCo's as two unrelated typical states are from each other: " +
      'the rollout has decorrelated (it still moves plausibly, but no longer as MuJoCo does from the same start); the table gives the gap in metres and degrees (90° or more: the attitudes are unrelated). ',
    h('span', { class: 'here' }, here),
  );
}

/** Root position (m), attitude (deg) and joint angles (rad) against MuJoCo, mean and p90 at each time. */
function physicalTable(m: ModelDetail, e: EvalResult | null): HTMLElement {
  const rows = splitServed(m, physicalRows(e)).shown;
  if (!rows.length)
    return h('p', { class: 'muted not-measured' }, 'Errors in physical units: not measured. ', h('code', {}, `neuro eval ${m.model} --json`), ' measures them.');
  const times = [...new Set(rows.flatMap((r) => r.values.map((v) => v.t_s)))].sort((a, b) => a - b);
  return h(
    'table',
    { class: 'grid physical', id: `physical-${m.model}` },
    h('caption', {}, 'The same in physical units: mean / 90th percentile over the trials'),
    h('tr', {}, h('th', {}, 'n'), h('th', {}, 'quantity'), ...times.map((t) => h('th', { class: 'num' }, `${fmt(t)} s`))),
    ...rows.map((r) =>
      h(
        'tr',
        {
          'data-version': r.version,
          'data-quantity': r.quantity,
          class: m.versions.includes(r.version) ? '' : 'not-served',
        },
        h('td', {}, servedLabel(r.substeps, m.versions.includes(r.version))),
        h('td', {}, PHYSICAL_QUANTITIES[r.quantity]),
        ...times.map((t) => {
          const v = r.values.find((x) => x.t_s === t);
          return h('td', { class: 'num' }, v ? `${physicalText(v.mean)} / ${physicalText(v.p90)}` : '–');
        }),
      ),
    ),
  );
}

function speedTable(model: string, b: BenchResult | null): HTMLElement {
  if (!b || (!b.single?.length && !b.batched?.length))
    return h('p', { class: 'muted not-measured' }, 'Speed: not measured. ', h('code', {}, `neuro bench ${model} --json`), ' measures it.');
  const out = h('div', { class: 'speed' });
  const folded = h('details', { class: 'more speed-more' }, h('summary', {}, speedSummary(b)), out);
  if (b.single?.length)
    out.append(
      h(
        'table',
        { class: 'grid' },
        h('caption', {}, 'One client, 20,000 physical steps (thesis Table 6.2)'),
        h('tr', {}, h('th', {}, 'n'), h('th', {}, 'MuJoCo (s)'), h('th', {}, 'emulator (s)'), h('th', {}, 'speed-up')),
        ...b.single.map((r) =>
          h('tr', {}, h('td', {}, `N^${r.substeps}`), h('td', {}, fmt(r.physics_s)), h('td', {}, fmt(r.emulator_s)), h('td', {}, `${fmt(r.ratio)}×`)),
        ),
      ),
    );
  if (b.batched?.length)
    out.append(
      h(
        'table',
        { class: 'grid' },
        h('caption', {}, `Batched clients (n = ${b.batched_substeps ?? '?'})`),
        h('tr', {}, h('th', {}, 'clients'), h('th', {}, 'MuJoCo steps/s'), h('th', {}, 'emulator steps/s'), h('th', {}, 'speed-up')),
        ...b.batched.map((r) =>
          h('tr', {}, h('td', {}, String(r.batch)), h('td', {}, fmt(r.physics_steps_per_s)), h('td', {}, fmt(r.emulator_steps_per_s)), h('td', {}, `${fmt(r.ratio)}×`)),
        ),
      ),
    );
  return folded;
}

/** The speed in one line: the best speed-up over MuJoCo, one client and batched. */
function speedSummary(b: BenchResult): string {
  const best = (xs: number[]): number | null => (xs.length ? Math.max(...xs) : null);
  const single = best((b.single ?? []).map((r) => r.ratio));
  const batched = best((b.batched ?? []).map((r) => r.ratio));
  const parts = [single !== null ? `up to ${fmt(single)}× MuJoCo's speed for one client` : '', batched !== null ? `${fmt(batched)}× batched` : ''].filter(Boolean);
  return `Speed: ${parts.join(', ')} (the tables)`;
}

export const modelsPage: Page = (root, ctx) => {
  let alive = true;
  let plots: LinePlot[] = [];
  const list = h('div', { class: 'models' }, h('p', { class: 'muted' }, 'Loading the emulators…'));
  const add = addModelPanel(ctx.trainer, ctx.emulator, () => void show()); // a new model: list it
  root.append(h('h1', {}, 'Models'), add.el, list);
  let shown = 0; // the latest listing wins over one still loading
  const show = async (): Promise<void> => {
    const mine = ++shown;
    const current = (): boolean => alive && mine === shown;
    try {
      const { models } = await ctx.emulator.models();
      if (!current()) return;
      plots.forEach((p) => p.dispose());
      plots = [];
      list.textContent = '';
      if (!models.length) {
        list.append(h('p', { class: 'muted' }, 'The emulator service has no models loaded. Add one above, or train one with make train MODEL=…'));
        return;
      }
      for (const s of models) {
        const card = h('section', { class: 'card model-card', 'data-model': s.model }, h('h2', {}, s.model));
        list.append(card);
        const measured = await measuredFiles(s.model);
        const [m, ev, bench] = await Promise.all([ctx.emulator.model(s.model), loadEval(s.model, measured), loadBench(s.model, measured)]);
        if (!current()) return;
        card.append(
          h('p', { class: 'desc' }, m.description || ''),
          h(
            'div',
            { class: 'cols' },
            h('div', {}, facts(m), h('h3', {}, 'Inputs'), inputs(m), h('h3', {}, 'State layout'), layout(m), h('h3', {}, 'Training'), metrics(m)),
            h('div', {}, h('h3', {}, 'Accuracy'), rolloutPlot(m, ev, plots), physicalTable(m, ev), speedTable(s.model, bench)),
          ),
        );
      }
    } catch (e) {
      if (!current()) return;
      list.textContent = '';
      list.append(h('p', { class: 'error-text' }, errorText(e)));
      notify(errorText(e));
    }
  };
  void show();
  return () => {
    alive = false;
    add.dispose();
    plots.forEach((p) => p.dispose());
  };
};
