// Models: "Add a model" (addmodel.ts: upload a MuJoCo model and train it), then every loaded emulator
// with its manifest (layout, controls, δt and n), training metrics, the rollout error over time (thesis
// Fig. 6.6), the errors in physical units (metres, degrees, radians) and the speed table (thesis
// Table 6.2) when measured. Curves and rows of versions the emulator service does not serve are
// labelled so.
import type { ModelDetail } from '../api/emulator.gen';
import { controlMeaning } from '../session/inputs';
import { errorText } from '../api/http';
import { curvesOf, loadBench, loadEval, PHYSICAL_QUANTITIES, physicalRows, servedLabel, type BenchResult, type EvalResult } from '../api/measurements';
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
    ['physics δt', `${fmt(m.timestep)} s`],
    ['super-step Δt = n·δt', `${fmt(m.super_timestep)} s (n = ${m.substeps})`],
    ['versions loaded', m.versions.join(', ')],
  ];
  return h('table', { class: 'facts' }, ...rows.map(([k, v]) => h('tr', {}, h('th', {}, k), h('td', {}, v))));
}

function inputs(m: ModelDetail): HTMLElement {
  const rows = [
    ...m.controls.map((c) => ['control', c.name, `${fmt(c.low)} … ${fmt(c.high)}`, controlMeaning(c)]),
    ...m.forces.map((f) => ['force', f.name, `${fmt(f.low)} … ${fmt(f.high)}`, '']),
  ];
  if (!rows.length) return h('p', { class: 'muted' }, 'No inputs: a passive model.');
  return h(
    'table',
    { class: 'grid inputs' },
    h('tr', {}, h('th', {}, 'input'), h('th', {}, 'name'), h('th', {}, 'trained range'), h('th', {}, 'what 1 applies; positive')),
    ...rows.map((r) => h('tr', {}, ...r.map((v) => h('td', {}, v)))),
  );
}

function layout(m: ModelDetail): HTMLElement {
  return h(
    'table',
    { class: 'grid' },
    h('tr', {}, h('th', {}, 'state group'), h('th', {}, 'kind'), h('th', {}, 'values')),
    ...m.layout.map((g) =>
      h('tr', {}, h('td', {}, g.name), h('td', {}, g.kind), h('td', {}, `[${g.offset}:${g.offset + g.size}] ${(g.labels ?? []).join(' ')}`)),
    ),
  );
}

function metrics(m: ModelDetail): HTMLElement {
  const got = METRICS.filter(([k]) => typeof m.metrics?.[k] === 'number');
  if (!got.length) return h('p', { class: 'muted' }, 'No training metrics in the manifest.');
  return h('table', { class: 'facts' }, ...got.map(([k, label]) => h('tr', {}, h('th', {}, label), h('td', {}, fmt(m.metrics?.[k] as number)))));
}

function rolloutPlot(m: ModelDetail, e: EvalResult | null, plots: LinePlot[]): HTMLElement {
  const curves = curvesOf(e);
  if (!curves.length)
    return h('p', { class: 'muted not-measured' }, 'Rollout error: not measured. ', h('code', {}, `neuro eval ${m.model} --json`), ' measures it.');
  const plot = new LinePlot({ logY: true, xLabel: 'time (s)', yLabel: 'normalised error', height: 230 });
  plots.push(plot);
  const series = curves.map((c, i) => {
    const served = m.versions.includes(c.version);
    return { name: servedLabel(c.substeps, served), xs: c.curve.t, ys: c.curve.error, color: COLORS[i % COLORS.length]!, dash: served ? undefined : [6, 4] };
  });
  const figure = h(
    'figure',
    { class: 'rollout' },
    h('figcaption', {}, 'Rollout error against MuJoCo over time, by super-step n (thesis Fig. 6.6)'),
    plot.el,
  );
  // drawn once the figure is in the page (the plot takes its element's width)
  queueMicrotask(() => plot.set(series));
  return figure;
}

/** Root position (m), attitude (deg) and joint angles (rad) against MuJoCo, mean and p90 at each time. */
function physicalTable(m: ModelDetail, e: EvalResult | null): HTMLElement {
  const rows = physicalRows(e);
  if (!rows.length)
    return h('p', { class: 'muted not-measured' }, 'Errors in physical units: not measured. ', h('code', {}, `neuro eval ${m.model} --json`), ' measures them.');
  const times = [...new Set(rows.flatMap((r) => r.values.map((v) => v.t_s)))].sort((a, b) => a - b);
  return h(
    'table',
    { class: 'grid physical', id: `physical-${m.model}` },
    h('caption', {}, 'Rollout error against MuJoCo in physical units: mean / 90th percentile over the trials'),
    h('tr', {}, h('th', {}, 'n'), h('th', {}, 'quantity'), ...times.map((t) => h('th', { class: 'num' }, `${fmt(t)} s`))),
    ...rows.map((r) =>
      h(
        'tr',
        { 'data-version': r.version, 'data-quantity': r.quantity, class: m.versions.includes(r.version) ? '' : 'not-served' },
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
  if (b.single?.length)
    out.append(
      h(
        'table',
        { class: 'grid' },
        h('caption', {}, 'One client, 20,000 physical steps (thesis Table 6.2)'),
        h('tr', {}, h('th', {}, 'n'), h('th', {}, 'MuJoCo (s)'), h('th', {}, 'emulator (s)'), h('th', {}, 'speed-up')),
        ...b.single.map((r) => h('tr', {}, h('td', {}, `N^${r.substeps}`), h('td', {}, fmt(r.physics_s)), h('td', {}, fmt(r.emulator_s)), h('td', {}, `${fmt(r.ratio)}×`))),
      ),
    );
  if (b.batched?.length)
    out.append(
      h(
        'table',
        { class: 'grid' },
        h('caption', {}, `Batched clients (n = ${b.batched_substeps ?? '?'})`),
        h('tr', {}, h('th', {}, 'clients'), h('th', {}, 'MuJoCo steps/s'), h('th', {}, 'emulator steps/s'), h('th', {}, 'speed-up')),
        ...b.batched.map((r) => h('tr', {}, h('td', {}, String(r.batch)), h('td', {}, fmt(r.physics_steps_per_s)), h('td', {}, fmt(r.emulator_steps_per_s)), h('td', {}, `${fmt(r.ratio)}×`))),
      ),
    );
  return out;
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
        const [m, ev, bench] = await Promise.all([ctx.emulator.model(s.model), loadEval(s.model), loadBench(s.model)]);
        if (!current()) return;
        card.append(
          h('p', { class: 'desc' }, m.description || ''),
          h(
            'div',
            { class: 'cols' },
            h('div', {}, facts(m), h('h3', {}, 'Inputs'), inputs(m), h('h3', {}, 'State layout'), layout(m), h('h3', {}, 'Training'), metrics(m)),
            h('div', {}, h('h3', {}, 'Accuracy'), rolloutPlot(m, ev, plots), physicalTable(m, ev), h('h3', {}, 'Speed'), speedTable(s.model, bench)),
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
