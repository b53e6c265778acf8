// End-to-end checks of the dashboard in headless Chromium (browser.mjs: the browser, the environment,
// the shared checks). tests/e2e/test_dashboard.py starts the stack and runs this.
//
//   node tests/e2e/dashboard.mjs <phase>     phase: models | playground | controllers | worker-down | frame-rate
//
// Environment: browser.mjs's, TRUCK_TASK (the truck-parking task's name, optional), and for frame-rate
// (bench/dashboard_fps.py) FPS_SETTLE, FPS_WINDOWS and FPS_SECONDS.
import { canvasStats, changed, check, frameRate, frameWindows, log, main, noErrorNotice, onScreen, out, shot, url } from './browser.mjs';

async function models(page) {
  // every request the page makes is for something that exists (no 404 for a result not measured)
  const failed = [];
  page.on('response', (r) => {
    if (r.status() >= 400) failed.push(`${r.status()} ${r.url()}`);
  });
  await page.goto(url('models'));
  await page.waitForSelector('.model-card .facts', { timeout: 30000 });
  // every card is filled in by its own calls: wait for the ones checked below, whatever their order
  await page.waitForFunction(
    () => ['lander', 'truck', 'pendulum-active'].every((m) => document.querySelector(`.model-card[data-model="${m}"] .facts`)),
    null,
    { timeout: 30000 },
  );
  const names = await page.$$eval('.model-card', (els) => els.map((e) => e.dataset.model));
  log(`models: ${names.join(', ')}`);
  check(['lander', 'truck', 'pendulum-active'].every((m) => names.includes(m)), `the default models are listed (got ${names})`);
  await page.waitForFunction(() => document.querySelectorAll('.rollout .uplot').length > 0 || document.querySelectorAll('.not-measured').length > 0, null, { timeout: 10000 });
  // every curve is of a version the emulator serves, or says it is not loaded
  const cards = await page.$$eval('.model-card', (els) =>
    els.map((card) => {
      const loaded = [...card.querySelectorAll('.facts tr')].find((tr) => tr.textContent.startsWith('versions loaded'));
      const legend = [...card.querySelectorAll('.rollout .u-legend .u-label')].map((l) => l.textContent);
      const series = JSON.parse(card.querySelector('.rollout .plot')?.dataset.series ?? '[]');
      const physical = [...card.querySelectorAll('table.physical tr[data-quantity]')].map((tr) => ({
        version: tr.dataset.version,
        quantity: tr.dataset.quantity,
        served: !tr.classList.contains('not-served'),
        cells: [...tr.querySelectorAll('td.num')].map((td) => td.textContent),
      }));
      return { model: card.dataset.model, loaded: loaded?.querySelector('td')?.textContent ?? '', legend, series, physical };
    }),
  );
  let curves = 0;
  for (const c of cards) {
    curves += c.series.length;
    for (const name of c.legend) check(c.series.includes(name), `${c.model}: the legend names a drawn curve (${name})`);
    for (const r of c.physical) check(c.loaded.split(', ').includes(r.version) === r.served, `${c.model}: ${r.version} is marked served only when loaded`);
    const notLoaded = c.series.filter((n) => /not loaded/.test(n)).length;
    check(c.series.length - notLoaded <= Math.max(1, c.loaded.split(', ').length), `${c.model}: only loaded versions are unlabelled (${c.series} vs ${c.loaded})`);
  }
  for (const c of cards) {
    const served = c.loaded.split(', ');
    check(c.series.every((n) => !/not loaded/.test(n)) || c.series.length === c.series.filter((n) => /not loaded/.test(n)).length, `${c.model}: versions not loaded are named, not drawn beside the loaded ones (${c.series})`);
    check(c.physical.every((r) => served.includes(r.version)) || c.physical.every((r) => !r.served), `${c.model}: the physical table shows the loaded versions`);
  }
  // what the numbers mean, in words, beside each measured curve
  await page.waitForFunction(() => document.querySelectorAll('.model-card').length === document.querySelectorAll('.model-card .cols').length, null, { timeout: 30000 });
  const meanings = await page.$$eval('.error-meaning', (els) => els.map((e) => e.textContent));
  log(`error explanations: ${meanings.length}; the lander's: ${meanings.find((t) => /N\^50/.test(t))?.slice(-90)}`);
  check(meanings.length === cards.filter((c) => c.series.length).length && meanings.length > 0, 'every rollout curve has an explanation of what its error means');
  check(meanings.every((t) => /About 1 means the emulated state is as far from MuJoCo's as two unrelated typical states/.test(t) && /decorrelated/.test(t)), 'the explanation says what an error of about 1 means');
  const ball = await page.$eval('.model-card[data-model="ball"] .error-meaning .here', (el) => el.textContent).catch(() => '');
  log(`ball: ${ball}`);
  // long state layouts are folded, and the page is short enough to read down
  const layouts = await page.$$eval('.model-card', (els) => els.map((c) => ({ model: c.dataset.model, open: [...c.querySelectorAll('.cols table.grid')].filter((t) => !t.closest('details') || t.closest('details').open).reduce((n, t) => Math.max(n, t.querySelectorAll('tr').length), 0) })));
  log(`longest open table per card: ${layouts.map((l) => `${l.model} ${l.open}`).join(', ')}`);
  check(layouts.every((l) => l.open <= 14), 'no card shows a table longer than a dozen rows unfolded');
  const height = await page.evaluate(() => document.documentElement.scrollHeight);
  log(`page height: ${height} px at 1280×800; failed requests: ${failed.length}`);
  out.page_height = height;
  check(height < 6000, `the Models page is under 6000 px long (${height})`);
  check(failed.length === 0, `the page asks only for what exists (${failed.join(', ')})`);
  const lander = cards.find((c) => c.model === 'lander');
  log(`rollout curves: ${curves}; lander physical rows: ${lander.physical.map((r) => `${r.quantity}@${r.version}`).join(', ')}`);
  check(lander.physical.some((r) => r.quantity === 'root_position_m' && r.cells.length === 4 && r.cells.every((x) => / \/ /.test(x))), 'the lander shows its root position error (mean / p90) at 4 times');
  check(lander.physical.some((r) => r.quantity === 'attitude_deg'), 'the lander shows its attitude error');
  out.models = names.length;
  out.rollout_curves = curves;
  await noErrorNotice(page, 'models');
  await shot(page, 'models');
}

async function startSession(page, model) {
  await page.selectOption('#pg-model', model);
  await page.click('#pg-start');
  await page.waitForFunction(
    (m) => document.querySelector('#pg-model')?.value === m && /t = /.test(document.querySelector('#pg-status')?.textContent ?? '') && !/Starting/.test(document.querySelector('#pg-status')?.textContent ?? ''),
    model,
    { timeout: 20000 },
  );
  await page.waitForTimeout(1200); // the camera glides to the model
}

/** A lander session started at rest 20 m above its pad (as its MJCF puts it), with the main jet where
 * the page found that it holds the lander still (hover thrust: mass 100 under lunar gravity, 10 N per
 * unit: 16.2), and the lander's height once the first state came. */
async function hoveringLander(page) {
  await page.goto(url('playground', 'model=lander&start=rest'));
  await page.waitForFunction(() => document.querySelector('#pg-model')?.value === 'lander', null, { timeout: 20000 });
  await page.click('#pg-start');
  await page.waitForSelector('[data-control="main_jet"]', { timeout: 20000 });
  const jet = Number(await page.$eval('[data-control="main_jet"]', (el) => el.value));
  const said = await page.$eval('#pg-hold', (el) => el.textContent).catch(() => '');
  log(`the main jet starts at ${jet}: ${said}`);
  check(Math.abs(jet - 16.2) < 1.5, `the lander starts at hover thrust, not with its jet off (${jet})`);
  check(/hold it still: main_jet/.test(said), 'the page says why the jet starts on');
  await page.waitForFunction(() => (document.querySelector('#pg-status')?.dataset.state ?? '') !== '', null, { timeout: 20000 });
  return JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state))[2];
}

async function playground(page) {
  // hover thrust: a few seconds later the lander is still about where it started, not falling through
  // its pad, and the camera shows it with the ground and the pad below it
  const z0 = await hoveringLander(page);
  await page.waitForTimeout(5000);
  const z1 = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state))[2];
  const held = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  log(`hovering: height ${z0} m -> ${z1} m after ${held} s`);
  check(held >= 3 && Math.abs(z1 - z0) < 2, `the lander hovers where it starts (${z0} -> ${z1} m over ${held} s)`);
  await onScreen(page, '#pg-view', 'model');
  const pad = await onScreen(page, '#pg-view', 'ground');
  log(`the ground below the lander is on screen at ${pad.x},${pad.y}; framing: ${await page.$eval('#pg-view', (el) => el.dataset.framing)}`);
  // and full thrust from the key for a second and a half
  await page.focus('body');
  await page.keyboard.down('ArrowUp');
  await page.waitForFunction(() => /t = /.test(document.querySelector('#pg-status')?.textContent ?? ''), null, { timeout: 20000 });
  log('lander session is live');
  const a = await canvasStats(page, '#pg-view canvas');
  await page.waitForTimeout(1500);
  const jet = await page.$eval('[data-control="main_jet"]', (el) => el.closest('.slider').querySelector('.value').textContent);
  await page.keyboard.up('ArrowUp');
  log(`main jet while the key was held: ${jet}`);
  check(Number(jet) > 30, 'holding ↑ drives the main jet to its high end');
  const b = await canvasStats(page, '#pg-view canvas');
  const moved = changed(a, b);
  log(`${moved} of ${a.total} cells changed`);
  check(moved > 20, 'the picture changes as the lander moves');
  // 20 m up the lander is framed alone, big enough to see, with the sky above the horizon
  const m0 = await onScreen(page, '#pg-view', 'model');
  const vbox = await page.$eval('#pg-view', (el) => ({ w: el.clientWidth, h: el.clientHeight }));
  const sky = await canvasStats(page, '#pg-view canvas', [[vbox.w * 0.1, 4]]);
  const [sr, , sb] = sky.colours[0];
  const framing = await page.$eval('#pg-view', (el) => el.dataset.framing);
  log(`lander at ${m0.x},${m0.y}; framing: ${framing}; sky colour at the top: ${sky.colours[0]}`);
  check(sb > sr + 15, 'the sky (blue) is at the top of the view');
  // the MuJoCo ghost, and how far it is from the emulator, as a number and a curve
  await page.check('#pg-ghost');
  await page.waitForFunction(() => document.querySelector('#pg-divergence')?.dataset.position !== undefined, null, { timeout: 10000 });
  await onScreen(page, '#pg-view', 'ghost');
  await page.waitForTimeout(1500);
  const gap = await page.$eval('#pg-divergence', (el) => ({ position: Number(el.dataset.position), text: el.querySelector('.gap-now').textContent, points: Number(el.querySelector('.plot').dataset.points) }));
  log(`divergence: ${gap.text} (${gap.points} points plotted)`);
  check(Number.isFinite(gap.position) && /root position error: .* m · root attitude error: .*°/.test(gap.text) && gap.points >= 2, 'the gap to MuJoCo is shown as a number and a curve');
  // the gap's readout is a small corner of the view, clear of its middle and of the model
  const over = await page.evaluate(() => {
    const r = document.querySelector('#pg-divergence').getBoundingClientRect();
    const c = document.querySelector('#pg-view canvas').getBoundingClientRect();
    return { x: r.left - c.left, y: r.top - c.top, w: r.width, h: r.height, cw: c.width, ch: c.height };
  });
  const lander = await onScreen(page, '#pg-view', 'model');
  const share = (over.w * over.h) / (over.cw * over.ch);
  const covers = (px, py) => px >= over.x && px <= over.x + over.w && py >= over.y && py <= over.y + over.h;
  log(`gap readout ${over.w.toFixed(0)}×${over.h.toFixed(0)} at ${over.x.toFixed(0)},${over.y.toFixed(0)}: ${(100 * share).toFixed(1)} % of the view; the lander at ${lander.x},${lander.y}`);
  check(share < 0.08, `the gap readout covers under 8 % of the view (${(100 * share).toFixed(1)} %)`);
  check(!covers(over.cw / 2, over.ch / 2) && !covers(lander.x, lander.y), 'the gap readout covers neither the middle of the view nor the model');
  // the ticked checkbox keeps the focus, and the keys still drive
  const focused = await page.evaluate(() => document.activeElement?.id ?? '');
  await page.keyboard.down('ArrowUp');
  await page.waitForTimeout(800);
  const jet2 = await page.$eval('[data-control="main_jet"]', (el) => el.closest('.slider').querySelector('.value').textContent);
  await page.keyboard.up('ArrowUp');
  log(`main jet with the focus on #${focused} and ↑ held: ${jet2}`);
  check(focused === 'pg-ghost' && Number(jet2) > 30, 'holding ↑ after ticking the ghost still drives the main jet');
  await shot(page, 'playground');
  const rate = await frameRate(page, 5);
  log(`dashboard frame rate with a live session: ${rate.fps.toFixed(1)} fps at resolution scale ${rate.scale}`);
  out.fps = Number(rate.fps.toFixed(1));
  out.resolution_scale = rate.scale;
  out.changed_cells = moved;

  // driven hard (full thrust, a roll jet) the lander leaves the states the emulator was trained on: the
  // page says so, beside the sliders and as a notice
  await page.focus('body');
  await page.keyboard.down('ArrowUp');
  await page.keyboard.down('KeyW');
  await page.waitForFunction(() => !document.querySelector('#pg-envelope')?.hidden, null, { timeout: 40000 });
  await page.keyboard.up('KeyW');
  await page.keyboard.up('ArrowUp');
  const envelope = await page.$eval('#pg-envelope', (el) => el.textContent);
  const notices = await page.$$eval('.notice-warning', (els) => els.map((e) => e.textContent));
  const driven = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  log(`out of the envelope at t = ${await page.$eval('#pg-status', (el) => el.dataset.t)} s (velocity ${driven.slice(7, 10)}, rates ${driven.slice(10, 13)}): ${envelope}`);
  check(envelope.length > 0 && notices.some((n) => /left the emulator's trained envelope/.test(n)), 'leaving the training envelope is shown');
  await onScreen(page, '#pg-view', 'model');

  // a second session without reloading: the camera frames the new model and the ground below it
  await startSession(page, 'pendulum-force');
  const m1 = await onScreen(page, '#pg-view', 'model');
  const g1 = await onScreen(page, '#pg-view', 'ground');
  const box = await page.$eval('#pg-view', (el) => ({ w: el.clientWidth, h: el.clientHeight }));
  log(`second session: pendulum at ${m1.x},${m1.y}, ground below it at ${g1.x},${g1.y} in ${box.w}×${box.h}`);
  check(Math.abs(m1.x - box.w / 2) < box.w * 0.35 && Math.abs(m1.y - box.h / 2) < box.h * 0.4, 'the second model is framed near the middle');
  // the bottom of the view is ground (grey), not sky
  const px = await canvasStats(page, '#pg-view canvas', [0.2, 0.5, 0.8].map((f) => [box.w * f, box.h - 6]));
  log(`colours along the bottom of the view: ${JSON.stringify(px.colours)}`);
  check(px.colours.every(([r, g, bl]) => Math.abs(r - bl) < 45 && r + g + bl > 150), 'the ground is drawn below the pendulum');
  // its pushes say what they apply and in what unit
  const meanings = await page.$$eval('.slider', (els) => els.filter((el) => el.querySelector('[data-force]')).map((el) => el.querySelector('.meaning')?.textContent ?? ''));
  log(`what the pushes apply: ${JSON.stringify(meanings)}`);
  check(meanings.length === 3 && meanings.every((t) => /push along the world x axis .* in N$/.test(t)), 'each push names its axis, its body and its unit');
  // pendulum-force: sliders for its pushes drive the session's forces; it hangs at rest until pushed
  const still = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  const pushes = await page.$$eval('[data-force]', (els) => els.map((e) => e.dataset.force));
  log(`force sliders: ${pushes.join(', ')}`);
  check(pushes.length === 3, 'pendulum-force has a slider for each of its 3 pushes');
  await page.$$eval('[data-force]', (els) =>
    els.forEach((el) => {
      el.value = el.max;
      el.dispatchEvent(new Event('input', { bubbles: true }));
    }),
  );
  await page.waitForTimeout(1500);
  const sent = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.sent ?? '{}'));
  const t1 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  await page.waitForTimeout(1200);
  const t2 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  log(`sent ${JSON.stringify(sent)}; session time ${t1} -> ${t2}`);
  check(sent.forces?.length === 3 && sent.forces.every((f) => f === 2) && sent.controls?.length === 3, 'the session is sent 3 controls and 3 forces, each push at its high end');
  check(t2 > t1, 'the session keeps stepping with the forces');
  const pushed = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  log(`joint angles at rest ${still.slice(0, 3)}, pushed ${pushed.slice(0, 3)}`);
  check(still.slice(0, 3).every((a) => Math.abs(a) < 0.05), 'the pendulum starts hanging at rest (the emulator drifts a little there)');
  check(Math.max(...[0, 1, 2].map((i) => Math.abs(pushed[i] - still[i]))) > 0.02, 'the push moves the pendulum');
  await onScreen(page, '#pg-view', 'model');
  await noErrorNotice(page, 'pendulum-force');
  await shot(page, 'playground-pendulum-force');

  // a third: the dolphin, drawn as a smooth skin over its 23 nodes, bent by its six muscles
  await startSession(page, 'dolphin');
  const skins = JSON.parse(await page.$eval('#pg-view', (el) => el.dataset.skins ?? '[]'));
  log(`dolphin skins: ${JSON.stringify(skins)}`);
  check(skins.length === 1 && skins[0].vertices === 23 && skins[0].triangles === 40, 'the dolphin is drawn as one skin of 23 vertices and 40 triangles');
  await onScreen(page, '#pg-view', 'model');
  const muscles = await page.$$eval('[data-control]', (els) => els.map((e) => e.dataset.control));
  check(muscles.length === 6, `the dolphin has a slider for each of its six muscles (${muscles.join(', ')})`);
  const rest = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  const d0 = await canvasStats(page, '#pg-view canvas');
  await page.$$eval('[data-control]', (els) =>
    els.forEach((el) => {
      el.value = el.dataset.control.startsWith('dorsal') ? el.max : el.min; // every dorsal muscle pulls: the body arches
      el.dispatchEvent(new Event('input', { bubbles: true }));
    }),
  );
  await page.waitForTimeout(3000);
  const bent = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  const moved3 = Math.max(...rest.slice(0, 69).map((v, i) => Math.abs(bent[i] - v)));
  const d1 = await canvasStats(page, '#pg-view canvas');
  log(`dolphin: largest node displacement ${moved3.toFixed(3)} m; ${changed(d0, d1)} cells changed`);
  check(moved3 > 0.02, 'the muscles bend the body');
  check(changed(d0, d1) > 5, 'the skin follows the nodes on screen');
  await noErrorNotice(page, 'dolphin');
  await shot(page, 'playground-dolphin');

  // a fourth: the runner, driven by its own running controller; the person sets its target speed
  await page.selectOption('#pg-model', 'runner');
  await page.waitForFunction(() => document.querySelector('#pg-start-from')?.value === 'driver', null, { timeout: 10000 });
  await startSession(page, 'runner');
  const speed = await page.$$eval('[data-driver]', (els) => els.map((e) => [e.dataset.driver, e.min, e.max, e.value]));
  const runnerControls = await page.$$eval('[data-control]', (els) => els.length);
  const runnerForces = await page.$$eval('[data-force]', (els) => els.map((e) => e.dataset.force));
  log(`runner: driver sliders ${JSON.stringify(speed)}, ${runnerControls} control sliders, forces ${runnerForces}`);
  check(speed.length === 1 && speed[0][0] === 'speed', 'the runner has a target-speed slider for its controller');
  check(runnerControls === 0 && runnerForces.length === 2, 'its joint targets come from the controller; the pushes are the person\'s');
  const r0 = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  const rt0 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  await page.$eval('[data-driver="speed"]', (el) => {
    el.value = el.max;
    el.dispatchEvent(new Event('input', { bubbles: true }));
  });
  await page.waitForTimeout(1000);
  const r1 = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.state));
  const rt1 = Number(await page.$eval('#pg-status', (el) => el.dataset.t));
  const runnerSent = JSON.parse(await page.$eval('#pg-status', (el) => el.dataset.sent ?? '{}'));
  log(`runner: x ${r0[0]} -> ${r1[0]} m, pelvis height ${r1[2]} m over ${(rt1 - rt0).toFixed(2)} s; sent ${JSON.stringify(runnerSent.driver)}`);
  check(r1[0] - r0[0] > 1.0 * (rt1 - rt0) && rt1 > rt0, 'the emulated runner runs forward');
  check(runnerSent.driver?.speed === 2.4, 'the target speed goes to the session');
  await onScreen(page, '#pg-view', 'model');
  await onScreen(page, '#pg-view', 'ghost');
  await shot(page, 'playground-runner');
  await page.click('#pg-stop');
}

async function submitAndReplay(page) {
  const t0 = Date.now();
  await page.click('#ct-submit');
  await page.waitForFunction(() => Number(document.querySelector('#objective-plot')?.dataset.points ?? 0) >= 3, null, { timeout: 180000 });
  log('the objective curve is updating');
  await page.waitForSelector('#replay .replay-view canvas', { timeout: 240000 });
  out.job_s = (Date.now() - t0) / 1000;
}

/** The outcome shown is the job result's, check by check, on both sides; the status line agrees. */
async function outcomeMatchesResult(page) {
  const job = await page.$eval('#job-status', (el) => el.dataset.job);
  const controller = await page.evaluate(async () => (await (await fetch('config.json')).json()).controller_url);
  const result = await page.evaluate(async (u) => (await fetch(u)).json(), `${controller}/jobs/${job}/result`);
  const shown = await page.$eval('#outcome', (el) => ({
    emulator: el.dataset.successEmulator,
    physics: el.dataset.successPhysics,
    criterion: el.querySelector('.criterion').textContent,
    rows: [...el.querySelectorAll('tr.check-row')].map((tr) => [tr.children[0].textContent, tr.children[1].dataset.passed, tr.children[2].dataset.passed]),
    // each value sits under its column's heading ("emulator", "MuJoCo"), not beside the check's text
    aligned: [...el.querySelectorAll('tr.check-row')].every((tr) => {
      const heads = el.querySelectorAll('table.checks tr:first-child th');
      return [1, 2].every((k) => Math.abs(tr.children[k].getBoundingClientRect().left - heads[k].getBoundingClientRect().left) < 2);
    }),
  }));
  check(shown.aligned, "the checks table's values are under their columns");
  const status = await page.$eval('#job-status', (el) => el.textContent);
  log(`status: ${status}`);
  log(`criterion: ${shown.criterion}; checks ${JSON.stringify(shown.rows)}`);
  check(shown.physics === String(result.success_physics) && shown.emulator === String(result.success_emulator), "the verdicts shown are the result's");
  check(shown.criterion.includes(result.success_criterion), "the criterion shown is the job's");
  check(shown.rows.length === result.checks_physics.length, 'one row per check');
  shown.rows.forEach(([text, emu, phys], i) => {
    check(text === result.checks_physics[i].check, `check ${i} is named as the service names it`);
    check(emu === String(result.checks_emulator[i].passed) && phys === String(result.checks_physics[i].passed), `check ${i}: passed as the service says`);
  });
  check(/meets the success criterion on MuJoCo/.test(status) === (result.success_physics === true), 'the status line agrees with the result on MuJoCo');
  check(!/succeeded/.test(status), 'the status line does not call a job "succeeded" (that is its run, not the criterion)');
  const verdict = await page.$eval('#outcome', (el) => [el.dataset.verdict, el.querySelector('#verdict')?.textContent ?? '']);
  log(`verdict: ${result.verdict}; shown ${JSON.stringify(verdict)}`);
  check(verdict[0] === result.verdict && verdict[1].includes(result.verdict), "the verdict shown is the result's");
  check((result.verdict === 'succeeded') === (result.success_physics === true), 'a job succeeds only when its controller meets the criterion on MuJoCo');
  return result.success_physics;
}

/** In each replay view, at the end of the replay, the model and its goal are on screen and the model is
 * drawn big enough to read (a sixth of the view's height or more across). */
async function replayFramesModelAndGoal(page, what) {
  await page.locator('#replay .replay-views').scrollIntoViewIfNeeded(); // a view out of sight is not drawn
  await page.$eval('#replay-time', (el) => {
    el.value = '1';
    el.dispatchEvent(new Event('input', { bubbles: true }));
  });
  await page.waitForTimeout(1500); // the camera glides to the end of the path
  for (const side of ['Emulator', 'MuJoCo (physics)']) {
    const view = `#replay .replay-view[data-side="${side}"]`;
    const model = await onScreen(page, view, 'model');
    await onScreen(page, view, 'goal');
    const box = await page.$eval(view, (el) => ({ w: el.clientWidth, h: el.clientHeight }));
    log(`${what} replay, ${side}: the model drawn ${model.w}×${model.h} px in ${box.w}×${box.h}`);
    check(Math.max(model.w, model.h) >= box.h / 6, `${what}: the replayed model is drawn big enough to read (${model.w}×${model.h} px in a view ${box.h} px tall)`);
  }
}

/** How much more cyan than red the pixels around the model's middle are, in a replay view (the mean of
 * (g + b) / 2 - r over a 5×5 grid 3 px apart). */
async function cyanAtModel(page, side) {
  const view = `#replay .replay-view[data-side="${side}"]`;
  const m = await onScreen(page, view, 'model');
  const pts = [];
  for (let i = -2; i <= 2; i++) for (let j = -2; j <= 2; j++) pts.push([m.x + 3 * i, m.y + 3 * j]);
  const px = await canvasStats(page, `${view} canvas`, pts);
  return px.colours.reduce((s, [r, g, b]) => s + (g + b) / 2 - r, 0) / px.colours.length;
}

/** Mid-flight (away from the goal drawn over the model at the end), the emulated body under the MuJoCo
 * outline keeps its own colours: it is little more cyan than the same body on the MuJoCo side. */
async function emulatedBodyReadable(page, what) {
  const emulator = await cyanAtModel(page, 'Emulator');
  const physics = await cyanAtModel(page, 'MuJoCo (physics)');
  log(`${what} replay: cyan excess around the model, emulator ${emulator.toFixed(0)}, MuJoCo ${physics.toFixed(0)}`);
  check(emulator - physics < 35, `${what}: the emulated body is not washed cyan by the MuJoCo outline (${emulator.toFixed(0)} vs ${physics.toFixed(0)})`);
}

/** Part way through a replay (for a screenshot of the motion). */
async function replayAt(page, share) {
  await page.$eval(
    '#replay-time',
    (el, v) => {
      el.value = String(v);
      el.dispatchEvent(new Event('input', { bubbles: true }));
    },
    share,
  );
  await page.waitForTimeout(1500);
}

async function controllers(page) {
  const task = process.env.TRUCK_TASK;
  await page.goto(url('controllers', task ? `task=${encodeURIComponent(task)}` : ''));
  await page.waitForFunction(() => document.querySelector('#ct-view')?.dataset.screenGoal && !document.querySelector('#ct-submit')?.disabled, null, { timeout: 30000 });
  const chosen = await page.$eval('#ct-task', (el) => el.value);
  log(`task: ${chosen}`);
  // drag the goal 80 px to the right on the ground
  const before = await page.$$eval('#ct-target input', (els) => els.map((e) => Number(e.value)));
  const goal = await onScreen(page, '#ct-view', 'goal');
  const box = await (await page.$('#ct-view canvas')).boundingBox();
  await page.mouse.move(box.x + goal.x, box.y + goal.y);
  await page.mouse.down();
  for (let i = 1; i <= 8; i++) await page.mouse.move(box.x + goal.x + i * 10, box.y + goal.y + i * 3);
  await page.mouse.up();
  await page.waitForTimeout(800);
  const after = await page.$$eval('#ct-target input', (els) => els.map((e) => Number(e.value)));
  log(`goal before ${before.slice(0, 3)} after the drag ${after.slice(0, 3)}`);
  check(before.length >= 2 && (after[0] !== before[0] || after[1] !== before[1]), 'dragging the goal moves it');
  out.goal_moved = Math.hypot(after[0] - before[0], after[1] - before[1]);
  await submitAndReplay(page);
  const objectives = JSON.parse(await page.$eval('#objective-plot', (el) => el.dataset.objectives ?? '[]')).filter((v) => v !== null);
  log(`objective: ${objectives[0]} -> ${objectives[objectives.length - 1]} over ${objectives.length} iterations`);
  check(objectives.length >= 3 && Math.min(...objectives.slice(1)) < objectives[0], 'the objective goes down');

  out.success_physics = await outcomeMatchesResult(page);

  const t1 = Number(await page.$eval('#replay', (el) => el.dataset.t ?? '0'));
  await page.waitForTimeout(1500);
  const t2 = Number(await page.$eval('#replay', (el) => el.dataset.t ?? '0'));
  log(`replay clock ${t1} -> ${t2}`);
  check(t2 > t1, 'the replay plays');
  await replayFramesModelAndGoal(page, 'truck');
  const gap = await page.$eval('#replay-divergence', (el) => Number(el.querySelector('.plot').dataset.points));
  check(gap >= 10, `the replay plots the gap between the emulator and MuJoCo over time (${gap} points)`);
  await replayAt(page, 0.6);
  await page.locator('#replay').scrollIntoViewIfNeeded();
  await page.waitForTimeout(500);
  await shot(page, 'replay');
  await page.evaluate(() => window.scrollTo(0, 0));
  await shot(page, 'controllers');
  out.iterations = objectives.length;
  out.objective_first = objectives[0];
  out.objective_last = objectives[objectives.length - 1];

  // another task: the job shown is dropped, and the lander and its goal are framed on screen
  await page.selectOption('#ct-task', 'lander-landing');
  await page.waitForFunction(() => !document.querySelector('#ct-submit')?.disabled && document.querySelector('#ct-view')?.dataset.screenModel, null, { timeout: 20000 });
  const cleared = await page.evaluate(() => ({
    replay: document.querySelectorAll('#replay').length,
    status: document.querySelector('#job-status').textContent,
    points: document.querySelector('#objective-plot').dataset.points,
  }));
  log(`after switching task: ${JSON.stringify(cleared)}`);
  check(cleared.replay === 0 && cleared.status === 'No job yet.' && cleared.points === '0', 'switching task clears the job, its curve and its replay');
  const lander = await onScreen(page, '#ct-view', 'model', 20);
  const pad = await onScreen(page, '#ct-view', 'goal', 20);
  log(`lander at ${lander.x},${lander.y}; its goal at ${pad.x},${pad.y}`);
  check(Math.hypot(lander.x - pad.x, lander.y - pad.y) > 60, 'the lander and its goal are apart on screen, both visible');
  await shot(page, 'controllers-lander');
  // the lander's job: its outcome as the result states it, its replay with the lander and the pad in view
  await submitAndReplay(page);
  out.lander_success_physics = await outcomeMatchesResult(page);
  await replayFramesModelAndGoal(page, 'lander');
  await replayAt(page, 0.4);
  await emulatedBodyReadable(page, 'lander');
  await page.locator('#replay').scrollIntoViewIfNeeded();
  await shot(page, 'replay-lander');
  await page.evaluate(() => window.scrollTo(0, 0));
  // a task whose model has no heading shows no heading control
  await page.selectOption('#ct-task', 'pendulum-swing');
  await page.waitForFunction(() => !document.querySelector('#ct-submit')?.disabled, null, { timeout: 20000 });
  check(!(await page.isVisible('#ct-heading')), 'the pendulum task shows no goal heading');

  // dolphin-swim: as far as it can, so no goal to drag or type; learned through the global network,
  // replayed on the emulator and on MuJoCo side by side with the body drawn as its skin
  await page.selectOption('#ct-task', 'dolphin-swim');
  await page.waitForFunction(() => !document.querySelector('#ct-submit')?.disabled && document.querySelector('#ct-view')?.dataset.screenModel, null, { timeout: 30000 });
  await page.waitForTimeout(600);
  check(!(await page.$eval('#ct-view', (el) => el.dataset.screenGoal ?? '')), 'dolphin-swim draws no goal');
  check((await page.$$('#ct-target input')).length === 0, 'dolphin-swim has no goal state to type');
  await submitAndReplay(page);
  const job = await page.$eval('#job-status', (el) => el.dataset.job);
  const controller = await page.evaluate(async () => (await (await fetch('config.json')).json()).controller_url);
  const swim = await page.evaluate(async (u) => (await fetch(u)).json(), `${controller}/jobs/${job}/result`);
  log(`dolphin-swim: ${swim.iterations} iterations through the ${swim.bptt_networks} network(s), J emulator ${swim.objective}, MuJoCo ${swim.objective_physics}`);
  check(swim.bptt_networks === 'global' && swim.iterations <= 20, 'dolphin-swim learns through the global network in at most 20 iterations');
  const said = await page.$eval('#outcome', (el) => el.textContent);
  check(/global network alone/.test(said) && /No goal state/.test(said), 'the outcome says there is no goal state and that BPTT used the global network');
  // a task without a success criterion: its run ended normally ("succeeded" to the job's state) but
  // the report says it is done with no criterion, and still gives what the controller reached
  const swimStatus = await page.$eval('#job-status', (el) => ({ text: el.textContent, state: el.dataset.status, verdict: el.dataset.verdict }));
  const swimVerdict = await page.$eval('#verdict', (el) => el.textContent);
  log(`dolphin-swim: job ${swimStatus.state}, verdict ${swim.verdict}; status line: ${swimStatus.text}`);
  check(swim.status === 'succeeded' && swim.verdict === 'done, no criterion', 'the job without a criterion ran to its end and its verdict is "done, no criterion"');
  check(/Done, no criterion/.test(swimStatus.text) && !/succeeded/.test(swimStatus.text) && /objective is .* on MuJoCo/.test(swimStatus.text), 'the status line says done, no criterion, with what the controller reached');
  check(swimStatus.verdict === 'done, no criterion' && /done, no criterion/.test(swimVerdict), 'the outcome shows the verdict "done, no criterion"');
  for (const side of ['Emulator', 'MuJoCo (physics)']) await onScreen(page, `#replay .replay-view[data-side="${side}"]`, 'model');
  await page.locator('#replay').scrollIntoViewIfNeeded();
  await page.waitForTimeout(500);
  await shot(page, 'replay-dolphin');
  out.dolphin_objective_physics = swim.objective_physics;
}

async function workerDown(page) {
  const task = process.env.TRUCK_TASK;
  await page.goto(url('controllers', task ? `task=${encodeURIComponent(task)}` : ''));
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
  await shot(page, 'worker-down');
  const id = await page.$eval('#job-status', (el) => el.dataset.job ?? '');
  if (id) await page.click('#ct-cancel'); // leave no job behind for a later worker
}

/** The frame rate of the Playground with a live lander session and its MuJoCo ghost (the lander at rest
 * 20 m up at hover thrust, the camera on it and its pad), after FPS_SETTLE seconds, over
 * FPS_WINDOWS windows of FPS_SECONDS seconds. */
async function frameRatePhase(page) {
  const settle = Number(process.env.FPS_SETTLE ?? 10);
  const windows = Number(process.env.FPS_WINDOWS ?? 6);
  const seconds = Number(process.env.FPS_SECONDS ?? 5);
  await hoveringLander(page);
  await page.check('#pg-ghost');
  await page.waitForFunction(() => document.querySelector('#pg-divergence')?.dataset.position !== undefined, null, { timeout: 20000 });
  log(`live session with its ghost; settling for ${settle} s`);
  await page.waitForTimeout(settle * 1000);
  const rows = await frameWindows(page, windows, seconds);
  for (const r of rows) log(`${r.fps.toFixed(1)} fps, ${r.late} late frames of ${r.frames}, resolution scale ${r.scale}`);
  out.windows = rows.map((r) => ({ ...r, fps: Number(r.fps.toFixed(2)) }));
  out.renderer = await page.evaluate(() => {
    const gl = document.createElement('canvas').getContext('webgl2');
    const info = gl?.getExtension('WEBGL_debug_renderer_info');
    return gl && info ? String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL)) : 'unknown';
  });
  await noErrorNotice(page, 'frame-rate');
}

await main({ models, playground, controllers, 'worker-down': workerDown, 'frame-rate': frameRatePhase }, { 'worker-down': () => true });
