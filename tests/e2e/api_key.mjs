// The dashboard against services that ask for API keys (API_KEYS set), in headless Chromium (browser.mjs:
// the browser and the shared checks). tests/e2e/test_api_key.py starts such a stack and runs this.
//
//   node tests/e2e/api_key.mjs api-key
//
// Without a key, the Models page says in plain words that a key is needed and where to enter it; with
// the key entered in the header's form, the models list, a Playground session (REST to start it, the
// websocket to drive it) and a controller job followed live (its event stream) all work; the key is kept
// for the next visit and can be forgotten.
// Environment: browser.mjs's, API_KEY (a key the stack accepts).
import { check, log, main, noErrorNotice, out, shot, url } from './browser.mjs';

async function apiKey(page) {
  const key = process.env.API_KEY;
  check(key, 'API_KEY is set');
  await page.goto(url('models'));
  await page.waitForSelector('.notice-error', { timeout: 20000 });
  const asked = await page.$$eval('.notice-error', (els) => els.map((e) => e.textContent).join(' | '));
  log(`without a key: ${asked}`);
  check(/key button/.test(asked), 'the page says that a key is needed and where to enter it');
  check((await page.$$('.model-card')).length === 0, 'no model is listed without a key');

  await page.click('[data-testid="key-button"]');
  await page.fill('[data-testid="key-input"]', key);
  await page.click('[data-testid="key-save"]');
  await page.waitForSelector('.model-card[data-model="pendulum-active"]', { timeout: 20000 });
  check((await page.textContent('[data-testid="key-button"]')) === 'API key: set', 'the header says a key is set');
  await noErrorNotice(page, 'models with the key');
  check(!(await page.content()).includes(key), 'the key is not written into the page');

  // the key is kept: a new visit drives a session (REST start, then the websocket with ?api_key=)
  await page.goto(url('playground'));
  await page.waitForFunction(() => document.querySelector('#pg-model')?.value === 'pendulum-active', null, { timeout: 20000 });
  await page.click('#pg-start');
  await page.waitForFunction(() => /t = /.test(document.querySelector('#pg-status')?.textContent ?? ''), null, { timeout: 20000 });
  const t1 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  await page.waitForTimeout(1500);
  const t2 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  log(`session time ${t1} -> ${t2} s`);
  check(t2 > t1, 'the live session advances over its websocket');
  await noErrorNotice(page, 'playground with the key');
  await shot(page, 'playground-with-key');
  await page.click('#pg-stop');

  // a controller job, followed live over its event stream (EventSource with ?api_key=)
  await page.goto(url('controllers', 'task=pendulum-swing'));
  await page.waitForFunction(() => document.querySelector('#ct-task')?.value === 'pendulum-swing' && !document.querySelector('#ct-submit')?.disabled, null, { timeout: 30000 });
  await page.click('#ct-submit');
  await page.waitForFunction(() => Number(document.querySelector('#objective-plot')?.dataset.points ?? 0) >= 3, null, { timeout: 120000 });
  log('the job is followed live');
  await page.waitForSelector('#replay .replay-view canvas', { timeout: 180000 });
  await noErrorNotice(page, 'controllers with the key');

  // forgotten: the next call is refused again, in the same plain words
  await page.click('[data-testid="key-button"]');
  await page.click('[data-testid="key-forget"]');
  await page.goto(url('models'));
  await page.waitForSelector('.notice-error', { timeout: 20000 });
  check(/key button/.test(await page.textContent('.notice-error')), 'without the key the page asks for it again');
  out.session_t = [t1, t2];
}

// the calls made without a key are refused (401), which Chromium reports on the console
await main({ 'api-key': apiKey }, { 'api-key': (e) => /status of 401/.test(e) });
