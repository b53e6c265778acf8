// The Policies page end to end in headless Chromium (browser.mjs: the browser, the environment, the
// shared checks). tests/e2e/test_policies.py starts the stack and runs this.
//
//   node tests/e2e/policies.mjs policies
//
// A lander-landing policy is trained through the dashboard with a small budget (15 s, no refinement:
// wide enough that a busy machine still shows it running at its second iteration); its progress
// shows live (iterations, the loss curve, the success on MuJoCo at its checks, MuJoCo steps), then
// the stored policy's metrics. "Drive it" starts a session driven by it beside its MuJoCo
// ghost; the goal (the pad) is dragged in the view, the websocket carries the new goal, the replies
// echo it and the lander moves. A goal typed outside the trained range is flagged as the service flags
// it, and a kick goes on from a kicked state in a new session of the same policy.
//
//   node tests/e2e/policies.mjs runner
//
// The runner's stored running policy (runner-run) is driven from the page's address: its goal is a
// command (a speed), set with a slider and drawn nowhere; the runner runs at it beside its ghost, the
// camera with it, and a push slider pushes it.
import { check, log, main, noErrorNotice, onScreen, out, screenOf, shot, url } from './browser.mjs';

const num = (s) => JSON.parse(s || 'null');

async function policies(page) {
  // every goal the page sends over a session's websocket
  const sent = [];
  page.on('websocket', (ws) => {
    ws.on('framesent', (f) => {
      const text = typeof f.payload === 'string' ? f.payload : '';
      if (text.includes('"goal"')) sent.push({ url: ws.url(), msg: JSON.parse(text) });
    });
  });

  // ---------------------------------------------------------------- train
  // seed=3: the session's start, the same every time (the screenshot under docs/)
  await page.goto(url('policies', 'task=lander-landing&seed=3'));
  await page.waitForSelector('#pt-tasks input[data-task="lander-landing"]:checked', { timeout: 20000 });
  const tasks = await page.$$eval('#pt-tasks tr[data-task]', (els) => els.map((e) => e.dataset.task));
  log(`policy tasks: ${tasks.join(', ')}`);
  check(['lander-landing', 'truck-parking', 'pendulum-swing', 'quadrotor-follow'].every((t) => tasks.includes(t)), 'the built-in policy tasks are listed');
  const none = await page.$eval('#pd-about', (el) => el.textContent);
  check(/train one below/.test(none), `with no stored policy the drive panel says to train one (${none})`);
  await page.fill('#pt-seconds', '15');
  await page.uncheck('#pt-refine');
  const t0 = Date.now();
  await page.click('#pt-train');
  // live: iterations and a loss curve while it runs, and a success share once MuJoCo checked it
  await page.waitForFunction(() => document.querySelector('#pt-status')?.dataset.status === 'running' && Number(document.querySelector('#pt-progress')?.dataset.iteration) >= 2, null, { timeout: 40000 });
  const live = await page.evaluate(() => ({
    iteration: Number(document.querySelector('#pt-progress').dataset.iteration),
    losses: Number(document.querySelector('#pt-loss').dataset.losses),
    status: document.querySelector('#pt-status').textContent,
  }));
  log(`live: ${JSON.stringify(live)}`);
  check(live.losses >= 2, 'the loss curve grows while the job runs');
  await page.waitForFunction(() => document.querySelector('#pt-progress')?.dataset.successPhysics !== '', null, { timeout: 30000 });
  const checked = await page.evaluate(() => ({
    status: document.querySelector('#pt-status').dataset.status,
    steps: Number(document.querySelector('#pt-progress').dataset.mujocoSteps),
    checks: Number(document.querySelector('#pt-success').dataset.checks),
  }));
  log(`checked on MuJoCo: ${JSON.stringify(checked)}`);
  check(checked.steps > 0 && checked.checks >= 1, 'the success on MuJoCo and the MuJoCo steps show as the job is checked');
  await page.waitForSelector('#pt-result:not([hidden]) #pt-metrics', { timeout: 60000 });
  out.training_s = (Date.now() - t0) / 1000;
  const result = await page.evaluate(() => ({
    status: document.querySelector('#pt-status').dataset.status,
    policy: document.querySelector('#pt-result').dataset.policy,
    success: document.querySelector('#pt-result').dataset.successPhysics,
    rows: Object.fromEntries([...document.querySelectorAll('#pt-metrics tr')].map((tr) => [tr.querySelector('th').textContent, tr.querySelector('td').textContent])),
    iterations: Number(document.querySelector('#pt-progress').dataset.iteration),
  }));
  log(`trained in ${out.training_s} s: ${JSON.stringify(result)}`);
  check(result.status === 'succeeded' && /^lander\/lander-landing\//.test(result.policy), 'the job succeeded and stored a lander-landing policy');
  check(/held-out runs/.test(result.rows['success on MuJoCo'] ?? '') && Number(result.rows.iterations) === result.iterations, "the stored policy's metrics are shown");
  out.policy = result.policy;
  out.success_physics = result.success === '' ? null : Number(result.success);
  await page.locator('#policy-train').scrollIntoViewIfNeeded();
  await shot(page, 'policies-train');

  // ---------------------------------------------------------------- drive
  await page.click('#pt-drive');
  await page.waitForFunction(() => (document.querySelector('#pd-status')?.dataset.state ?? '') !== '', null, { timeout: 20000 });
  await page.evaluate(() => window.scrollTo(0, 0));
  const chosen = await page.$eval('#pd-policy', (el) => el.value);
  check(chosen === 'lander/lander-landing', `Drive it picks the new policy (${chosen})`);
  await onScreen(page, '#pd-view', 'model', 4, 10000);
  await onScreen(page, '#pd-view', 'ghost', 4, 10000);
  const goal = await onScreen(page, '#pd-view', 'goal', 20, 10000);
  const before = num(await page.$eval('#pd-goal', (el) => el.dataset.goal));
  await page.waitForTimeout(800); // the camera settles on the lander and its pad
  const at = await onScreen(page, '#pd-view', 'goal', 20);
  const box = await (await page.$('#pd-view canvas')).boundingBox();
  const dx = at.x < box.width / 2 ? 80 : -80; // towards the middle of the view
  const sentBefore = sent.length;
  await page.mouse.move(box.x + at.x, box.y + at.y);
  await page.mouse.down();
  for (let i = 1; i <= 10; i++) await page.mouse.move(box.x + at.x + (i * dx) / 10, box.y + at.y + i * 3);
  await page.mouse.up();
  const after = num(await page.$eval('#pd-goal', (el) => el.dataset.goal));
  log(`goal on screen at ${goal.x},${goal.y} then ${at.x},${at.y}; goal ${JSON.stringify(before)} -> ${JSON.stringify(after)}`);
  check(before.length === 2 && Math.hypot(after[0] - before[0], after[1] - before[1]) > 0.5, 'dragging the pad moves the goal');
  // the websocket carried it, and the session's replies say it is the goal it drives to
  // (the service echoes float32 values: -10.1505 comes back as -10.1505003, so compare within a tolerance, not as rounded text)
  await page.waitForFunction((g) => {
    const echoed = JSON.parse(document.querySelector('#pd-status')?.dataset.goal || 'null');
    return Array.isArray(echoed) && echoed.length === g.length && echoed.every((v, i) => Math.abs(v - g[i]) < 1e-3);
  }, after, { timeout: 5000 });
  const goals = sent.slice(sentBefore).map((s) => s.msg);
  const last = goals[goals.length - 1];
  log(`goal messages during the drag: ${goals.length}; last ${JSON.stringify(last)}`);
  check(goals.length >= 1 && last.type === 'controls' && JSON.stringify(last.goal) === JSON.stringify(after) && !('controls' in last), 'the websocket sent the new goal (and no controls)');
  check(goals.length <= 20, `a drag sends a handful of goals, not one per pointer move (${goals.length})`);
  const s0 = num(await page.$eval('#pd-status', (el) => el.dataset.state));
  const t1 = Number(await page.$eval('#pd-status', (el) => el.dataset.t));
  await page.waitForTimeout(2000);
  const s1 = num(await page.$eval('#pd-status', (el) => el.dataset.state));
  const t2 = Number(await page.$eval('#pd-status', (el) => el.dataset.t));
  const moved = Math.hypot(s1[0] - s0[0], s1[1] - s0[1], s1[2] - s0[2]);
  const controls = num(await page.$eval('#pd-status', (el) => el.dataset.controls));
  log(`lander ${s0.slice(0, 3)} -> ${s1.slice(0, 3)} (${moved.toFixed(2)} m) over t ${t1} -> ${t2} s; controls ${controls}`);
  check(t2 > t1 && moved > 0.05, 'the lander moves, driven by the policy');
  check(Array.isArray(controls) && controls.length === 4, 'the replies carry the controls the policy chose');
  out.goal = after;
  out.moved_m = moved;
  await noErrorNotice(page, 'driving');
  await shot(page, 'policies');

  // a goal outside the trained range: flagged as the service flags it
  await page.fill('[data-goal-number="position.x"]', '22');
  await page.press('[data-goal-number="position.x"]', 'Enter');
  await page.waitForSelector('#pd-goal-outside:not([hidden])', { timeout: 5000 });
  const flag = await page.$eval('#pd-goal-outside', (el) => ({ outside: el.dataset.outside, text: el.textContent }));
  log(`outside: ${JSON.stringify(flag)}`);
  check(flag.outside === 'position.x' && /outside the range/.test(flag.text), 'a goal outside the trained range is flagged');
  await page.fill('[data-goal-number="position.x"]', '2');
  await page.press('[data-goal-number="position.x"]', 'Enter');
  await page.waitForSelector('#pd-goal-outside[hidden]', { state: 'attached', timeout: 5000 });

  // a kick: a new session of the same policy from a kicked state, the ghost with it
  const first = await page.$eval('#pd-status', (el) => el.dataset.session);
  await page.click('#pd-kick');
  await page.waitForFunction((id) => (document.querySelector('#pd-status')?.dataset.session ?? id) !== id && document.querySelector('#pd-status')?.dataset.kicks === '1', first, { timeout: 10000 });
  const kicked = num(await page.$eval('#pd-status', (el) => el.dataset.kicked));
  const echoed = num(await page.$eval('#pd-status', (el) => el.dataset.goal));
  log(`kicked to velocity ${kicked.slice(7, 10)}; goal ${JSON.stringify(echoed)}`);
  check(Math.abs(echoed[0] - 2) < 1e-3, 'the kicked session drives to the same goal');
  await noErrorNotice(page, 'after a kick');
  out.goal_messages = goals.length;
}

async function runner(page) {
  const sent = [];
  page.on('websocket', (ws) => {
    ws.on('framesent', (f) => {
      const text = typeof f.payload === 'string' ? f.payload : '';
      if (text.includes('"goal"')) sent.push(JSON.parse(text));
    });
  });
  await page.goto(url('policies', 'policy=runner/runner-run&drive=1&seed=1'));
  await page.waitForFunction(() => (document.querySelector('#pd-status')?.dataset.state ?? '') !== '', null, { timeout: 30000 });
  const hint = await page.$eval('#pd-goal-hint', (el) => el.textContent);
  check(/command/.test(hint), `the goal is offered as a command (${hint})`);
  const sliders = await page.$$eval('input[data-goal]', (els) => els.map((e) => e.dataset.goal));
  check(JSON.stringify(sliders) === '["speed"]', `one slider, the speed (${sliders})`);
  await onScreen(page, '#pd-view', 'model', 4, 10000);
  check((await screenOf(page, '#pd-view', 'goal')) === null, 'a command has no goal marker in the view');
  const forces = await page.$$eval('[data-force]', (els) => els.length);
  check(forces >= 2, `the runner can be pushed (${forces} force sliders)`);

  // a new command: sent over the websocket, echoed, and run at
  const before = sent.length;
  await page.fill('[data-goal-number="speed"]', '2.2');
  await page.press('[data-goal-number="speed"]', 'Enter');
  await page.waitForFunction(() => JSON.parse(document.querySelector('#pd-status')?.dataset.goal || 'null')?.[0]?.toFixed(2) === '2.20', null, { timeout: 5000 });
  const last = sent.slice(before).pop();
  check(last && JSON.stringify(last.goal) === '[2.2]' && !('controls' in last), `the websocket sent the command (${JSON.stringify(last)})`);
  await page.waitForTimeout(1000);
  const s0 = num(await page.$eval('#pd-status', (el) => el.dataset.state));
  const t0 = Number(await page.$eval('#pd-status', (el) => el.dataset.t));
  await page.waitForTimeout(2500);
  const s1 = num(await page.$eval('#pd-status', (el) => el.dataset.state));
  const t1 = Number(await page.$eval('#pd-status', (el) => el.dataset.t));
  const controls = num(await page.$eval('#pd-status', (el) => el.dataset.controls));
  const speed = Math.hypot(s1[0] - s0[0], s1[1] - s0[1]) / (t1 - t0);
  log(`runner ${s0.slice(0, 3)} -> ${s1.slice(0, 3)} over t ${t0} -> ${t1} s: ${speed.toFixed(2)} m/s; ${controls?.length} controls`);
  check(t1 > t0 && speed > 1.0 && s1[2] > 0.55, 'the runner runs, up, driven by the policy');
  check(Array.isArray(controls) && controls.length === 29, 'the replies carry the 29 servo targets the policy chose');
  await onScreen(page, '#pd-view', 'model', 4, 5000); // the camera went with it
  out.speed = speed;

  // a command outside the trained range is flagged
  await page.fill('[data-goal-number="speed"]', '3');
  await page.press('[data-goal-number="speed"]', 'Enter');
  await page.waitForSelector('#pd-goal-outside:not([hidden])', { timeout: 5000 });
  const flag = await page.$eval('#pd-goal-outside', (el) => el.dataset.outside);
  check(flag === 'speed', `a speed outside the trained range is flagged (${flag})`);
  await page.fill('[data-goal-number="speed"]', '2');
  await page.press('[data-goal-number="speed"]', 'Enter');
  await page.waitForSelector('#pd-goal-outside[hidden]', { state: 'attached', timeout: 5000 });
  await noErrorNotice(page, 'driving the runner');
  await shot(page, 'policies-runner');
}

await main({ policies, runner });
