// Shared by the end-to-end scripts (dashboard.mjs, add_model.mjs): headless Chromium (Debian's
// /usr/bin/chromium, driven by playwright-core from web/node_modules) at 1280×800, the checks and
// measurements they make of the page, and `main`, which runs the phase named on the command line.
//
// Environment: DASHBOARD_URL (required), SCREENSHOT_DIR (default tests/e2e/screenshots), CHROMIUM
// (default /usr/bin/chromium), DOCS=1 (draw at full resolution for the screenshots under docs/).
// A phase prints progress lines and, last, one JSON object {"phase", "ok", ...measurements} (`out`);
// it exits 1 on a failed check (the message says which) or on a console error it does not allow.
// Whether a model or a goal is on screen is read from the view's projection of it (data-screen-<name>
// on the view, written by the page's viewer), colours from the canvas' pixels.
import { mkdirSync, mkdtempSync, rmSync } from 'node:fs';
import { createRequire } from 'node:module';
import { tmpdir } from 'node:os';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';

export const root = resolve(dirname(fileURLToPath(import.meta.url)), '..', '..');
const require = createRequire(join(root, 'web', 'package.json'));
const { chromium } = require('playwright-core');

export const phase = process.argv[2] ?? '';
const base = process.env.DASHBOARD_URL;
if (!base) throw new Error('DASHBOARD_URL is not set');
const shots = process.env.SCREENSHOT_DIR ?? join(root, 'tests', 'e2e', 'screenshots');
mkdirSync(shots, { recursive: true });
export const out = { phase, ok: false };
// DOCS=1 (E2E_UPDATE_DOCS=1 in the test): views drawn at full resolution whatever the frame rate, for
// the screenshots under docs/
const full = process.env.DOCS === '1' ? 'resolution=full' : '';
export const url = (page, query = '') => `${base}/#/${page}${query || full ? '?' : ''}${[query, full].filter(Boolean).join('&')}`;

export function check(cond, message) {
  if (!cond) throw new Error(`check failed: ${message}`);
}

export function log(msg) {
  console.log(`[${phase}] ${msg}`);
}

/** A small fingerprint of a view's canvas (read in the page): per-cell brightness, and the colour at
 * given points of the canvas: [x, y] in CSS pixels, or the name of a mark of its view (where the object
 * is in the very picture read; `at` says where that was). */
export async function canvasStats(page, selector, points = []) {
  return page.evaluate(
    ([sel, pts]) => {
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
      const cells = [];
      for (let i = 0; i < d.length; i += 4) cells.push(d[i] + d[i + 1] + d[i + 2]);
      const sx = w / c.clientWidth;
      const marks = c.parentElement?.dataset ?? {};
      const at = pts.map((p) => (typeof p === 'string' ? (marks[`screen${p[0].toUpperCase()}${p.slice(1)}`] ?? '').split(',').slice(0, 2).map(Number) : p));
      const colours = at.map(([x, y]) => {
        const i = (Math.min(h - 1, Math.max(0, Math.round(y * sx))) * w + Math.min(w - 1, Math.max(0, Math.round(x * sx)))) * 4;
        return [d[i], d[i + 1], d[i + 2]];
      });
      return { total: w * h, cells, colours, at };
    },
    [selector, points],
  );
}

export function changed(a, b) {
  let n = 0;
  for (let i = 0; i < a.cells.length; i++) if (Math.abs(a.cells[i] - b.cells[i]) > 30) n += 1;
  return n;
}

/** Where an object the view marks is on its canvas and how big it is drawn: data-screen-<name>="x,y,on,w,h"
 * (viewer.mark). */
export async function screenOf(page, view, name) {
  const raw = await page.$eval(view, (el, n) => el.dataset[`screen${n[0].toUpperCase()}${n.slice(1)}`] ?? '', name);
  if (!raw) return null;
  const [x, y, on, w, h] = raw.split(',').map(Number);
  return { x, y, on: on === 1, w, h };
}

/** Waits until the view marks `name` on screen, inside the canvas with `inset` pixels to spare. */
export async function onScreen(page, view, name, inset = 4, timeout = 8000) {
  const t0 = Date.now();
  let s = null;
  let box = null;
  while (Date.now() - t0 < timeout) {
    s = await screenOf(page, view, name);
    box = await page.$eval(view, (el) => ({ w: el.clientWidth, h: el.clientHeight }));
    if (s && s.on && s.x >= inset && s.y >= inset && s.x <= box.w - inset && s.y <= box.h - inset) return s;
    await page.waitForTimeout(250);
  }
  const marks = await page.$eval(view, (el) => JSON.stringify(el.dataset));
  throw new Error(`check failed: the ${name} is on screen in ${view} (at ${JSON.stringify(s)} of ${JSON.stringify(box)}; marks ${marks})`);
}

export async function frameRate(page, seconds) {
  const f0 = await page.evaluate(() => ({ frames: window.__neuro?.frames ?? 0, t: performance.now() }));
  await page.waitForTimeout(seconds * 1000);
  const f1 = await page.evaluate(() => ({ frames: window.__neuro?.frames ?? 0, t: performance.now(), scale: window.__neuro?.scale ?? 1 }));
  return { fps: ((f1.frames - f0.frames) * 1000) / (f1.t - f0.t), scale: f1.scale };
}

/** `windows` windows of `seconds` each, back to back, timed in the page from its animation frames: per
 * window the frame rate, the frames that came late (an interval over 1.5 display frames: a vsync
 * missed) and the resolution scale at its end. */
export async function frameWindows(page, windows, seconds) {
  return page.evaluate(
    ([n, span]) =>
      new Promise((done) => {
        const rows = [];
        let start = -1;
        let prev = -1;
        let frames = 0;
        let late = 0;
        const tick = (t) => {
          if (start < 0) start = t;
          else {
            frames += 1;
            if (t - prev > 25) late += 1; // 1.5 frames of a 60 Hz display
          }
          prev = t;
          if (t - start >= span * 1000) {
            rows.push({ fps: (frames * 1000) / (t - start), late, frames, scale: window.__neuro?.scale ?? 1 });
            start = t;
            frames = 0;
            late = 0;
          }
          if (rows.length < n) requestAnimationFrame(tick);
          else done(rows);
        };
        requestAnimationFrame(tick);
      }),
    [windows, seconds],
  );
}

export async function noErrorNotice(page, what) {
  const errors = await page.$$eval('.notice-error', (els) => els.map((e) => e.textContent));
  check(errors.length === 0, `${what}: no error notice (got ${errors.join(' | ')})`);
}

export async function shot(page, name, opts = {}) {
  await page.screenshot({ path: join(shots, `${name}.png`), ...opts });
}

/**
 * Runs the phase named on the command line (one of `phases`: name -> async (page) => void) in a fresh
 * Chromium profile, then prints `out` and exits. `allowErrors[phase](text)` says which console errors
 * that phase expects (default: none).
 */
export async function main(phases, allowErrors = {}) {
  const run = phases[phase];
  if (!run) throw new Error(`unknown phase ${phase}; one of ${Object.keys(phases)}`);
  const allowed = allowErrors[phase] ?? (() => false);
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
    viewport: { width: 1280, height: 800 }, // the size of the screenshots in docs/
  });
  const errors = [];
  let code = 1;
  try {
    const page = browser.pages()[0] ?? (await browser.newPage());
    page.on('console', (m) => {
      // a failed load says which address failed
      if (m.type() === 'error') errors.push(m.location()?.url ? `${m.text()} (${m.location().url})` : m.text());
    });
    page.on('pageerror', (e) => errors.push(String(e)));
    await run(page);
    const unexpected = errors.filter((e) => !allowed(e));
    if (unexpected.length) throw new Error(`console errors: ${unexpected.join(' | ')}`);
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
}
