// "Add a model" end to end in headless Chromium (browser.mjs: the browser and the shared checks).
// tests/e2e/test_add_model.py starts a stack over an artifact registry of its own and runs this.
//
//   node tests/e2e/add_model.mjs <phase>     phase: add-model | add-model-refused
//
// add-model: MODEL_ZIP (the project's test model folder, zipped) is uploaded with a tiny budget; its
// progress shows live (phases, percent, loss curve) to the result, then "Drive it" opens the Playground
// on it and the model is drawn there, its knob from the folder's OBJ mesh.
// add-model-refused: bad models are refused at once, in the trainer service's words (an actuator with
// no ctrlrange; an MJCF uploaded without the file it includes; a file that is no model at all), and so
// is an operating spec naming an actuator the model does not have, beside the spec's box.
// Environment: browser.mjs's, MODEL_ZIP (add-model), NO_CTRLRANGE_XML, LONE_XML and SPEC_XML (a model
// that trains: add-model-refused).
import { readFileSync } from 'node:fs';
import { basename } from 'node:path';
import { canvasStats, check, log, main, noErrorNotice, onScreen, out, shot, url } from './browser.mjs';

/** The panel's status line (its data-* say the training's status, phase and percent). */
const statusOf = (page) => page.$eval('#am-status', (el) => ({ text: el.textContent, ...el.dataset }));

async function fillTinyBudget(page) {
  await page.fill('#am-super-step', '10');
  await page.fill('#am-examples', '200');
  await page.click('#add-model details.more summary');
  await page.fill('#am-epochs', '12');
  await page.fill('#am-hidden', '8');
  await page.fill('#am-rollout-steps', '0');
  await page.check('#am-force'); // a budget this small misses the accuracy bar: keep it anyway
}

/** Watches the training until it ends: the phases, percents and loss points the page showed. */
async function watchTraining(page, timeoutMs) {
  const seen = { phases: [], percents: [], lossPoints: [] };
  const t0 = Date.now();
  for (;;) {
    const s = await statusOf(page);
    // every phase the status line showed, however briefly (a tiny budget trains in a few ms)
    seen.phases = await page.evaluate(() => window.__amPhases.slice());
    if (s.percent !== undefined) seen.percents.push(Number(s.percent));
    seen.lossPoints.push(Number(await page.$eval('#am-loss', (el) => el.dataset.points ?? '0')));
    if (['succeeded', 'failed', 'cancelled'].includes(s.status)) return { ...seen, last: s };
    check(Date.now() - t0 < timeoutMs, `the training ends within ${timeoutMs / 1000} s (last: ${s.text})`);
    await page.waitForTimeout(150);
  }
}

async function addModel(page) {
  const zip = process.env.MODEL_ZIP;
  check(zip, 'MODEL_ZIP is set');
  await page.goto(url('models'));
  await page.waitForSelector('#am-file', { state: 'attached', timeout: 20000 });
  await page.setInputFiles('#am-file', zip);
  const chosen = await page.$eval('#am-chosen', (el) => el.textContent);
  log(`chosen: ${chosen}`);
  check(chosen.startsWith(basename(zip)), 'the drop zone names the chosen file');
  await fillTinyBudget(page);
  // a phase can last less than one poll of the page: record the status line's every change
  await page.evaluate(() => {
    const el = document.querySelector('#am-status');
    window.__amPhases = [];
    const note = () => {
      const p = el.dataset.phase;
      if (p && window.__amPhases[window.__amPhases.length - 1] !== p) window.__amPhases.push(p);
    };
    new MutationObserver(note).observe(el, { attributes: true, attributeFilter: ['data-phase'] });
  });
  const t0 = Date.now();
  await page.click('#am-submit');
  const seen = await watchTraining(page, 240000);
  out.training_s = (Date.now() - t0) / 1000;
  log(`phases shown: ${seen.phases.join(' → ')}; ${seen.last.text} (${out.training_s} s)`);
  check(seen.last.status === 'succeeded', `the training succeeds (${seen.last.text})`);
  check(seen.phases.includes('training') && seen.phases[seen.phases.length - 1] === 'done', 'the phases show live, through training to done');
  check(seen.percents.some((p) => p > 0 && p < 100), 'a percent between 0 and 100 showed while it ran');
  check(Math.max(...seen.lossPoints) >= 3, `the loss curve is drawn (${Math.max(...seen.lossPoints)} points)`);
  const steps = await page.$$eval('#am-phases .step', (els) => els.map((e) => e.dataset.state));
  check(steps.every((s) => s === 'done'), `every phase is done (${steps})`);
  const facts = await page.$$eval('#am-facts tr', (rows) => Object.fromEntries(rows.map((r) => [r.children[0].textContent, r.children[1].textContent])));
  log(`result: ${JSON.stringify(facts)}`);
  check(Number(facts['one-step error (1 − R²)']) > 0 && Number(facts['linear baseline']) > 0, 'the one-step error and the linear baseline are shown');
  check(await page.isVisible('#am-physical tr[data-quantity="joint_angle_rad"]'), 'the joint angle error in radians is shown');
  // "Drive it" once the emulator service serves the new version; the page lists it meanwhile
  await page.waitForSelector('#am-drive:not([disabled])', { timeout: 30000 });
  await page.waitForSelector('.model-card[data-model="tinybot"] .facts', { timeout: 20000 });
  await noErrorNotice(page, 'models');
  await page.evaluate(() => window.scrollTo(0, 0));
  await shot(page, 'models-add-model');
  out.phases = seen.phases;
  out.one_step_rel_error = Number(facts['one-step error (1 − R²)']);

  await page.click('#am-drive');
  await page.waitForFunction(() => location.hash.startsWith('#/playground') && document.querySelector('#pg-model')?.value === 'tinybot', null, { timeout: 20000 });
  await page.waitForFunction(() => /t = /.test(document.querySelector('#pg-status')?.textContent ?? ''), null, { timeout: 30000 });
  log('the Playground drives tinybot');
  await page.waitForFunction(() => document.querySelector('#pg-view')?.dataset.meshes, null, { timeout: 20000 });
  const meshes = JSON.parse(await page.$eval('#pg-view', (el) => el.dataset.meshes));
  log(`meshes drawn from their files: ${JSON.stringify(meshes)}`);
  check(meshes.length === 1 && meshes[0].geom === 'knob' && meshes[0].file.endsWith('.obj') && meshes[0].triangles === 12, "the knob is drawn from the folder's OBJ (12 triangles)");
  await page.waitForTimeout(1000); // the camera glides to the model
  await onScreen(page, '#pg-view', 'mesh');
  await onScreen(page, '#pg-view', 'model');
  // the knob's material (checker: rgba 1 1 1 1) makes it white where the rod keeps MuJoCo's default grey
  // (which the view draws at about 300 of 765 in r + g + b); read where the swinging knob is in that picture
  const px = await canvasStats(page, '#pg-view canvas', ['mesh']);
  const [r, g, b] = px.colours[0];
  log(`knob on screen at ${px.at[0]} in ${px.colours[0]}; its material colour ${meshes[0].color}`);
  check(meshes[0].color === '#ffffff', "the knob takes its material's colour");
  check(r + g + b > 420 && Math.max(r, g, b) - Math.min(r, g, b) < 40, 'the knob is drawn white on screen');
  await noErrorNotice(page, 'playground');
  await shot(page, 'playground-tinybot');
  await page.click('#pg-stop');
}

/** Uploads a file and returns the refusal the panel shows. */
async function refusalOf(page, file) {
  await page.setInputFiles('#am-file', file);
  if (await page.isEnabled('#am-submit')) await page.click('#am-submit');
  await page.waitForSelector('#am-error:not([hidden])', { timeout: 20000 });
  const text = await page.$eval('#am-error', (el) => el.textContent);
  log(`${file.name}: ${text}`);
  return text;
}

async function addModelRefused(page) {
  await page.goto(url('models'));
  await page.waitForSelector('#am-file', { state: 'attached', timeout: 20000 });
  const xml = (name, env) => ({ name, mimeType: 'text/xml', buffer: readFileSync(process.env[env]) });
  const noRange = await refusalOf(page, xml('noctrl.xml', 'NO_CTRLRANGE_XML'));
  check(/^This model cannot be trained: model noctrl: actuator 'push' has no ctrlrange/.test(noRange), 'the actuator without a ctrlrange is named');
  const lone = await refusalOf(page, xml('robot.xml', 'LONE_XML'));
  check(/^This model cannot be trained: .*parts\/arm\.xml/.test(lone), 'the missing include is named');
  const other = await refusalOf(page, { name: 'robot.urdf', mimeType: 'text/xml', buffer: Buffer.from('<robot/>') });
  check(/robot\.urdf is not a model the trainer takes/.test(other) && (await page.isDisabled('#am-submit')), 'a file of another kind is refused before it is sent');
  // a model that trains, with an operating spec that names an actuator it does not have
  await page.fill('#am-spec', '{"controls": {"thrust9": {"centre": 0.5}}}');
  await page.setInputFiles('#am-file', xml('slider.xml', 'SPEC_XML'));
  await page.click('#am-submit');
  await page.waitForSelector('#am-spec-error:not([hidden])', { timeout: 20000 });
  const spec = await page.$eval('#am-spec-error', (el) => el.textContent);
  log(`operating spec: ${spec}`);
  check(/operating_spec\.controls\.thrust9: the model has no actuator 'thrust9'; its controls are \['push'\]/.test(spec), 'the unknown actuator is named beside the spec');
  check(await page.isHidden('#am-error'), 'the model itself is not refused');
  await page.fill('#am-spec', '{"controls": {');
  await page.click('#am-submit');
  await page.waitForFunction(() => /not JSON/.test(document.querySelector('#am-spec-error')?.textContent ?? ''), null, { timeout: 5000 });
  const status = await statusOf(page);
  check(!status.training, 'no training was started');
  await noErrorNotice(page, 'refusals');
  out.refusals = [noRange, lone, other];
  out.spec_refusal = spec;
}

// Chromium reports on the console every load that fails: a refused upload (a 4xx), and the speed table
// of a model the trainer made, which nobody has measured (the Models page asks and shows "not measured")
const unmeasured = (e) => /status of 404 .*\/artifacts\/[^/]+\/bench\.json\)$/.test(e);
await main(
  { 'add-model': addModel, 'add-model-refused': addModelRefused },
  { 'add-model': unmeasured, 'add-model-refused': (e) => unmeasured(e) || /status of 4\d\d .*\/trainings\)$/.test(e) },
);
