// /docs (Swagger UI) and /redoc (ReDoc) of each service in headless Chromium with the network blocked:
// every request to a host other than 127.0.0.1 / localhost is aborted and recorded. Each page must
// render the service's operations and make no such request. tests/e2e/test_docs_offline.py starts the
// services and runs this.
//
//   SERVICE_URLS=name=http://127.0.0.1:PORT,... node tests/e2e/docs_offline.mjs
//
// Environment: SERVICE_URLS (required), SCREENSHOT_DIR (default tests/e2e/screenshots), CHROMIUM
// (default /usr/bin/chromium). Prints progress lines and, last, one JSON object {"ok", "pages": [...]};
// exits 1 on a failed check.
import { mkdirSync, mkdtempSync, rmSync } from 'node:fs';
import { createRequire } from 'node:module';
import { tmpdir } from 'node:os';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';

const root = resolve(dirname(fileURLToPath(import.meta.url)), '..', '..');
const require = createRequire(join(root, 'web', 'package.json'));
const { chromium } = require('playwright-core');

const spec = process.env.SERVICE_URLS;
if (!spec) throw new Error('SERVICE_URLS is not set');
const services = spec.split(',').map((s) => s.split('=', 2));
const shots = process.env.SCREENSHOT_DIR ?? join(root, 'tests', 'e2e', 'screenshots');
mkdirSync(shots, { recursive: true });
const LOCAL = new Set(['127.0.0.1', 'localhost', '[::1]']);
const out = { ok: false, pages: [] };

function check(cond, message) {
  if (!cond) throw new Error(`check failed: ${message}`);
}

// What each page shows once its script has run: the operations of the service's OpenAPI document.
const RENDERED = {
  docs: () => document.querySelectorAll('.swagger-ui .opblock').length,
  redoc: () => document.querySelectorAll('[data-section-id^="operation/"], [data-section-id^="tag/"]').length,
};

async function visit(context, name, base, kind) {
  const page = await context.newPage();
  const blocked = [];
  const errors = [];
  page.on('pageerror', (e) => errors.push(String(e)));
  page.on('console', (m) => {
    if (m.type() === 'error') errors.push(m.text());
  });
  await page.route('**/*', (route) => {
    const url = new URL(route.request().url());
    if (['http:', 'https:', 'ws:', 'wss:'].includes(url.protocol) && !LOCAL.has(url.hostname)) {
      blocked.push(url.href);
      return route.abort('internetdisconnected');
    }
    return route.continue();
  });
  await page.goto(`${base}/${kind}`, { waitUntil: 'load' });
  await page.waitForFunction(RENDERED[kind], null, { timeout: 30000 });
  await page.waitForLoadState('networkidle');
  const items = await page.evaluate(RENDERED[kind]);
  const text = await page.evaluate(() => document.body.innerText);
  await page.screenshot({ path: join(shots, `docs-${name}-${kind}.png`) });
  console.log(`[docs] ${name} /${kind}: ${items} items rendered, ${blocked.length} requests off this machine`);
  check(text.includes('NeuroAnimator'), `${name} /${kind} shows the service's title`);
  check(blocked.length === 0, `${name} /${kind} asks nothing of the internet (asked: ${blocked.join(' ')})`);
  check(errors.length === 0, `${name} /${kind} has no console errors (${errors.join(' | ')})`);
  out.pages.push({ service: name, page: kind, items, blocked });
  await page.close();
}

const profile = mkdtempSync(join(tmpdir(), 'neuro-e2e-docs-'));
const context = await chromium.launchPersistentContext(profile, {
  executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--disable-gpu', '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  viewport: { width: 1280, height: 800 },
});
let code = 1;
try {
  for (const [name, base] of services) {
    for (const kind of ['docs', 'redoc']) await visit(context, name, base, kind);
  }
  out.ok = true;
  code = 0;
} catch (e) {
  out.error = String(e?.message ?? e);
  console.log(`[docs] FAILED: ${out.error}`);
} finally {
  await context.close();
  rmSync(profile, { recursive: true, force: true });
}
console.log(JSON.stringify(out));
process.exit(code);
