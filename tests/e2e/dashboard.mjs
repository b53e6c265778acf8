// End-to-end checks of the dashboard in headless Chromium (Debian's /usr/bin/chromium, driven by
// playwright-core from web/node_modules). tests/e2e/test_dashboard.py starts the stack and runs this.
//
//   node tests/e2e/dashboard.mjs <phase>     phase: models | playground | controllers | worker-down
//
// Environment: DASHBOARD_URL (required), SCREENSHOT_DIR (default tests/e2e/screenshots), CHROMIUM
// (default /usr/bin/chromium), TRUCK_TASK (the truck-parking task's name, optional).
// Every phase prints progress lines and, last, one JSON object {"phase", "ok", ...measurements}; it
// exits 1 on a failed check (the message says which) or on a console error on the happy path.
import { mkdirSync, mkdtempSync, rmSync } from 'node:fs';
import { createRequire } from 'node:module';
import { tmpdir } from 'node:os';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';

const root = resolve(dirname(fileURLToPath(import.meta.url)), '..', '..');
const require = createRequire(join(root, 'web', 'package.json'));
const { chromium } = require('playwright-core');

const phase = process.argv[2] ?? 'models';
const base = process.env.DASHBOARD_URL;
if (!base) throw new Error('DASHBOARD_URL is not set');
const shots = process.env.SCREENSHOT_DIR ?? join(root, 'tests', 'e2e', 'screenshots');
mkdirSync(shots, { recursive: true });
const out = { phase, ok: false };

function check(cond, message) {
  if (!cond) throw new Error(`check failed: ${message}`);
}

function log(msg) {
  console.log(`[${phase}] ${msg}`);
}

/** Non-background pixels of the view's canvas and a small fingerprint of it (read in the page). */
async function canvasStats(page, selector) {
  return page.evaluate((sel) => {
    const c = document.querySelector(sel);
    if (!(c instanceof HTMLCanvasElement)) return null;
    const w = 160;
    const h = Math.max(1, Math.round((c.height / c.width) * w));
    const small = document.createElement('canvas');
    small.width = w;
    small.height = h;
    const g = small.getContext('2d');
    window.__neuroRedraw?.(c); // the view keeps no drawing buffer: draw it now and read it in this task
    g.drawImage(c, 0, 0, w, h);
    const d = g.getImageData(0, 0, w, h).data;
    const bg = [0x11, 0x16, 0x1d];
    let lit = 0;
    const cells = [];
    for (let i = 0; i < d.length; i += 4) {
      const diff = Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]);
      if (diff > 40) lit += 1;
      cells.push(d[i] + d[i + 1] + d[i + 2]);
    }
    return { lit, total: w * h, cells };
  }, selector);
}

function changed(a, b) {
  let n = 0;
  for (let i = 0; i < a.cells.length; i++) if (Math.abs(a.cells[i] - b.cells[i]) > 30) n += 1;
  return n;
}

async function frameRate(page, seconds) {
  const f0 = await page.evaluate(() => ({ frames: window.__neuro?.frames ?? 0, t: performance.now() }));
  await page.waitForTimeout(seconds * 1000);
  const f1 = await page.evaluate(() => ({ frames: window.__neuro?.frames ?? 0, t: performance.now() }));
  return ((f1.frames - f0.frames) * 1000) / (f1.t - f0.t);
}

async function models(page) {
  await page.goto(`${base}/#/models`);
  await page.waitForSelector('.model-card .facts', { timeout: 30000 });
  await page.waitForFunction(() => document.querySelectorAll('.model-card .facts').length >= 5, null, { timeout: 30000 });
  const names = await page.$$eval('.model-card', (els) => els.map((e) => e.dataset.model));
  log(`models: ${names.join(', ')}`);
  check(['lander', 'truck', 'pendulum-active'].every((m) => names.includes(m)), `the default models are listed (got ${names})`);
  const plots = await page.$$eval('.rollout svg polyline', (els) => els.length);
  const missing = await page.$$eval('.not-measured', (els) => els.length);
  log(`rollout curves drawn: ${plots}, "not measured" notes: ${missing}`);
  check(plots > 0 || missing > 0, 'each model shows its rollout error or says it was not measured');
  out.models = names.length;
  out.rollout_curves = plots;
  await page.screenshot({ path: join(shots, 'models.png'), fullPage: false });
}

async function playground(page) {
  await page.goto(`${base}/#/playground?model=lander`);
  await page.waitForFunction(() => document.querySelector('#pg-model')?.value === 'lander', null, { timeout: 20000 });
  await page.click('#pg-start');
  await page.waitForFunction(() => /t = /.test(document.querySelector('#pg-status')?.textContent ?? ''), null, { timeout: 20000 });
  log('lander session is live');
  await page.waitForTimeout(1500);
  const a = await canvasStats(page, '#pg-view canvas');
  check(a && a.lit > 50, `the view shows the model (${a?.lit} lit pixels of ${a?.total})`);
  // drive: full thrust and a roll for two seconds
  await page.focus('body');
  await page.keyboard.down('ArrowUp');
  await page.keyboard.down('KeyW');
  await page.waitForTimeout(2500);
  const jet = await page.$eval('[data-control="main_jet"]', (el) => el.closest('.slider').querySelector('.value').textContent);
  await page.keyboard.up('ArrowUp');
  await page.keyboard.up('KeyW');
  log(`main jet while the key was held: ${jet}`);
  check(Number(jet) > 30, 'holding ↑ drives the main jet to its high end');
  const b = await canvasStats(page, '#pg-view canvas');
  const moved = changed(a, b);
  log(`lit pixels ${a.lit} -> ${b.lit}; ${moved} of ${a.total} cells changed`);
  check(b.lit > 50 && moved > 20, 'the picture changes as the lander moves');
  // the MuJoCo ghost
  await page.check('#pg-ghost');
  await page.waitForTimeout(1500);
  await page.screenshot({ path: join(shots, 'playground.png') });
  const fps = await frameRate(page, 5);
  log(`dashboard frame rate with a live session: ${fps.toFixed(1)} fps`);
  out.fps = Number(fps.toFixed(1));
  out.lit_pixels = b.lit;
  out.changed_cells = moved;
  await page.click('#pg-stop');
}

async function controllers(page) {
  const task = process.env.TRUCK_TASK;
  await page.goto(`${base}/#/controllers${task ? `?task=${encodeURIComponent(task)}` : ''}`);
  await page.waitForFunction(() => document.querySelector('#ct-view')?.dataset.goal && !document.querySelector('#ct-submit')?.disabled, null, { timeout: 30000 });
  const chosen = await page.$eval('#ct-task', (el) => el.value);
  log(`task: ${chosen}`);
  // drag the goal 80 px to the right on the ground
  const before = await page.$$eval('#ct-target input', (els) => els.map((e) => Number(e.value)));
  const [gx, gy] = (await page.$eval('#ct-view', (el) => el.dataset.goal)).split(',').map(Number);
  const box = await (await page.$('#ct-view canvas')).boundingBox();
  await page.mouse.move(box.x + gx, box.y + gy);
  await page.mouse.down();
  for (let i = 1; i <= 8; i++) await page.mouse.move(box.x + gx + i * 10, box.y + gy + i * 3);
  await page.mouse.up();
  await page.waitForTimeout(800);
  const after = await page.$$eval('#ct-target input', (els) => els.map((e) => Number(e.value)));
  log(`goal before ${before.slice(0, 3)} after the drag ${after.slice(0, 3)}`);
  check(before.length >= 2 && (after[0] !== before[0] || after[1] !== before[1]), 'dragging the goal moves it');
  out.goal_moved = Math.hypot(after[0] - before[0], after[1] - before[1]);
  const t0 = Date.now();
  await page.click('#ct-submit');
  await page.waitForFunction(() => Number(document.querySelector('#objective-plot')?.dataset.points ?? 0) >= 3, null, { timeout: 180000 });
  log('the objective curve is updating');
  await page.waitForSelector('#replay .replay-view canvas', { timeout: 240000 });
  out.job_s = (Date.now() - t0) / 1000;
  const objectives = JSON.parse(await page.$eval('#objective-plot', (el) => el.dataset.objectives ?? '[]')).filter((v) => v !== null);
  log(`objective: ${objectives[0]} -> ${objectives[objectives.length - 1]} over ${objectives.length} iterations`);
  check(objectives.length >= 3 && Math.min(...objectives.slice(1)) < objectives[0], 'the objective goes down');
  const final = await page.$eval('#final-errors', (el) => el.textContent);
  log(`final errors: ${final}`);
  check(/Emulator/.test(final) && /MuJoCo/.test(final), 'the final errors are shown');
  const t1 = Number(await page.$eval('#replay', (el) => el.dataset.t ?? '0'));
  await page.waitForTimeout(1500);
  const t2 = Number(await page.$eval('#replay', (el) => el.dataset.t ?? '0'));
  log(`replay clock ${t1} -> ${t2}`);
  check(t2 > t1, 'the replay plays');
  const s = await canvasStats(page, '#replay .replay-view canvas');
  check(s && s.lit > 50, 'the replay shows the model');
  await page.waitForTimeout(1500);
  await page.locator('#replay').scrollIntoViewIfNeeded();
  await page.screenshot({ path: join(shots, 'controllers.png'), fullPage: true });
  out.iterations = objectives.length;
  out.objective_first = objectives[0];
  out.objective_last = objectives[objectives.length - 1];
  out.final_errors = final;
}

async function workerDown(page) {
  const task = process.env.TRUCK_TASK;
  await page.goto(`${base}/#/controllers${task ? `?task=${encodeURIComponent(task)}` : ''}`);
  await page.waitForFunction(() => !document.querySelector('#ct-submit')?.disabled, null, { timeout: 30000 });
  await page.click('#ct-submit');
  await page.waitForFunction(
    () => [...document.querySelectorAll('.notice')].some((n) => /no controller worker has started it/i.test(n.textContent ?? '')),
    null,
    { timeout: 60000 },
  );
  const text = await page.$$eval('.notice', (els) => els.map((e) => e.textContent).join(' | '));
  log(`notice: ${text}`);
  out.message = text;
  await page.screenshot({ path: join(shots, 'worker-down.png') });
  const id = await page.$eval('#job-status', (el) => el.dataset.job ?? '');
  if (id) await page.click('#ct-cancel'); // leave no job behind for a later worker
}

const PHASES = { models, playground, controllers, 'worker-down': workerDown };
const run = PHASES[phase];
if (!run) throw new Error(`unknown phase ${phase}; one of ${Object.keys(PHASES)}`);

const profile = mkdtempSync(join(tmpdir(), 'neuro-e2e-chromium-'));
// a fresh profile each run (launchPersistentContext passes it as --user-data-dir)
const browser = await chromium.launchPersistentContext(profile, {
  executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: [
    '--no-sandbox',
    '--disable-gpu',
    '--disable-quic',
    '--no-first-run',
    '--disable-background-networking',
    '--disable-component-update',
    '--disable-sync',
    // WebGL without a GPU: Chromium's software renderer
    '--use-angle=swiftshader',
    '--enable-unsafe-swiftshader',
  ],
  viewport: { width: 1400, height: 900 },
});
const errors = [];
let code = 1;
try {
  const page = browser.pages()[0] ?? (await browser.newPage());
  page.on('console', (m) => {
    if (m.type() === 'error') errors.push(m.text());
  });
  page.on('pageerror', (e) => errors.push(String(e)));
  await run(page);
  if (phase !== 'worker-down' && errors.length) throw new Error(`console errors: ${errors.join(' | ')}`);
  out.ok = true;
  code = 0;
} catch (e) {
  out.error = String(e?.message ?? e);
  out.console_errors = errors;
  console.log(`[${phase}] FAILED: ${out.error}`);
} finally {
  await browser.close();
  rmSync(profile, { recursive: true, force: true });
}
console.log(JSON.stringify(out));
process.exit(code);
