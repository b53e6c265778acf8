// Controllers: pick a task, set its goal by dragging the translucent target on the ground (or typing
// it), submit the job, watch the objective fall iteration by iteration (server-sent events), then
// replay the controller on the emulator and on MuJoCo side by side. Switching task drops the job shown.
import * as THREE from 'three';
import { FINAL_STATES, defaultTask, type JobResult, type JobStatus, type ProgressEvent, type TaskInfo } from '../api/controller';
import type { ModelDetail, ModelGeometry } from '../api/emulator.gen';
import { errorText } from '../api/http';
import { groundHeight, ModelView } from '../scene/model';
import { DropLine } from '../scene/trail';
import { makeViewer, meshFilesOf } from '../scene/setup';
import type { Viewer } from '../scene/viewer';
import { rootMoves } from '../scene/divergence';
import { hasGoalState, headingOf, NO_HANDLES, targetHandles, withHeading, withXY, type TargetHandles } from '../session/target';
import { fmt, h } from '../ui/dom';
import { clearNotice, notify } from '../ui/notices';
import { LinePlot } from '../ui/plot';
import type { Page } from './context';
import { GOAL_COLOR, MODEL_TRAIL } from './divergence';
import { outcomeSummary, verdictOf } from './outcome';
import { Replay } from './replay';

const QUEUED_WARN_S = 8;
const POLL_MS = 1500;

interface Scene {
  task: TaskInfo;
  detail: ModelDetail;
  geometry: ModelGeometry;
  handles: TargetHandles;
  target: number[];
  model: ModelView;
  goal: ModelView;
  drops: [DropLine, DropLine]; // below the model and below the goal
}

export const controllersPage: Page = (root, ctx) => {
  const taskSelect = h('select', { id: 'ct-task', 'aria-label': 'task' });
  const desc = h('p', { class: 'desc', id: 'ct-desc' }, 'Loading the tasks…');
  const editor = h('div', { class: 'target-editor', id: 'ct-target' });
  const heading = h('input', { type: 'range', min: -180, max: 180, step: 1, value: 0, id: 'ct-heading', 'aria-label': 'goal heading' });
  const headingRow = h('label', { class: 'heading-row', hidden: true }, 'Goal heading ', heading);
  const submitBtn = h('button', { id: 'ct-submit', class: 'primary', disabled: true }, 'Synthesise controller');
  const cancelBtn = h('button', { id: 'ct-cancel', disabled: true }, 'Cancel job');
  const jobStatus = h('div', { class: 'status', id: 'job-status' }, 'No job yet.');
  const plot = new LinePlot({ logY: true, xLabel: 'iteration', yLabel: 'objective', height: 240 });
  plot.el.id = 'objective-plot';
  const viewHost = h('div', { class: 'view', id: 'ct-view' });
  const replayHost = h('div', { id: 'replay-host' });
  root.append(
    h('h1', {}, 'Controllers'),
    h(
      'div',
      { class: 'split' },
      h(
        'aside',
        { class: 'panel' },
        h('label', {}, 'Task ', taskSelect),
        desc,
        h('p', { class: 'hint' }, 'Drag the green goal in the view (or type its values), then synthesise.'),
        headingRow,
        editor,
        h('div', { class: 'buttons' }, submitBtn, cancelBtn),
        jobStatus,
        h('figure', { class: 'objective' }, h('figcaption', {}, 'Objective per iteration (live)'), plot.el),
      ),
      viewHost,
    ),
    replayHost,
  );

  const viewer = makeViewer(viewHost);
  let tasks: TaskInfo[] = [];
  let scene: Scene | null = null;
  let alive = true;
  let job: { id: string; events: EventSource | null; poll: number; queuedSince: number; points: ProgressEvent[] } | null = null;
  let replay: Replay | null = null;

  // ---------------------------------------------------------------- the goal
  const poseGoal = async (): Promise<void> => {
    const s = scene;
    if (!s) return;
    try {
      const r = await ctx.emulator.poses(s.detail.model, [s.target], s.detail.version);
      if (scene !== s) return;
      s.goal.group.position.set(0, 0, 0);
      s.goal.setPoses(r.poses[0] ?? []);
      viewer?.keepInView(s.goal.visible ? [s.model.group, s.goal.group] : [s.model.group]);
    } catch (e) {
      notify(`Cannot place the goal. ${errorText(e)}`, 'error', 'goal');
    }
  };

  const drawEditor = (): void => {
    const s = scene;
    editor.textContent = '';
    if (!s) return;
    const labels = s.detail.state_labels;
    for (const i of s.handles.editable) {
      const input = h('input', { type: 'number', step: 0.1, value: (s.target[i] ?? 0).toFixed(3), 'data-index': i });
      input.addEventListener('change', () => {
        const v = Number(input.value);
        if (!Number.isFinite(v)) return;
        s.target[i] = v;
        void poseGoal();
      });
      editor.append(h('label', { class: 'num' }, h('span', {}, labels[i] ?? `s[${i}]`), input));
    }
    headingRow.hidden = !s.handles.heading;
    heading.value = String(Math.round((headingOf(s.target, s.handles) * 180) / Math.PI));
  };

  heading.addEventListener('input', () => {
    if (!scene) return;
    scene.target = withHeading(scene.target, scene.handles, (Number(heading.value) * Math.PI) / 180);
    drawEditor();
    void poseGoal();
  });

  const selectTask = async (name: string): Promise<void> => {
    const task = tasks.find((t) => t.name === name);
    if (!task) return;
    clearJob();
    if (scene) disposeScene(scene);
    scene = null;
    editor.textContent = '';
    headingRow.hidden = true;
    submitBtn.disabled = true;
    desc.textContent = task.description ?? '';
    if (!task.model) {
      desc.textContent = `Task ${task.name} names no model.`;
      return;
    }
    try {
      const [detail, geometry] = await Promise.all([ctx.emulator.model(task.model), ctx.emulator.geometry(task.model)]);
      const init = task.initial_state ?? null;
      const target = [...(task.target_state ?? init ?? [])];
      const files = meshFilesOf(ctx.emulator, geometry);
      const aimed = hasGoalState(task.state_weights); // dolphin-swim has no goal state: no goal drawn
      const s: Scene = {
        task,
        detail,
        geometry,
        handles: aimed ? targetHandles(detail.layout) : NO_HANDLES,
        target,
        model: new ModelView(geometry, {}, files),
        goal: new ModelView(geometry, { ghost: true, color: GOAL_COLOR, opacity: 0.3 }, files),
        drops: [new DropLine(MODEL_TRAIL), new DropLine(GOAL_COLOR, 0.9)],
      };
      if (!alive || taskSelect.value !== name) return;
      s.goal.visible = aimed;
      scene = s;
      const states = [init, target].filter((x): x is number[] => Array.isArray(x) && x.length === detail.state_size);
      const poses = states.length ? (await ctx.emulator.poses(detail.model, states, detail.version)).poses : [];
      if (init && poses[0]) s.model.setPoses(poses[0]);
      if (poses[poses.length - 1] && target.length) s.goal.setPoses(poses[poses.length - 1]!);
      if (viewer) {
        viewer.world.add(s.model.group, s.goal.group);
        // how high the model starts and the goal is, for a model that moves in the world
        if (rootMoves(detail.layout)) viewer.world.add(...s.drops.map((d) => d.group));
        viewer.setGroundHeight(groundHeight(s.model, poses.length ? poses : [geometry.rest_poses]));
        // the model where it starts and the goal, whole, with the ground below them
        viewer.frameObjects(aimed ? [s.model.group, s.goal.group] : [s.model.group]);
        void Promise.all([s.model.meshes, s.goal.meshes]).then(() => viewer.invalidate()); // drawn from their files
      }
      drawEditor();
      submitBtn.disabled = target.length !== detail.state_size;
      clearNotice('goal');
    } catch (e) {
      notify(`Cannot show task ${name}. ${errorText(e)}`, 'error', 'goal');
    }
  };
  taskSelect.addEventListener('change', () => void selectTask(taskSelect.value));

  // ---------------------------------------------------------------- dragging the goal on the ground
  const drag = viewer ? dragGoal(viewer, () => scene, (x, y) => {
    if (!scene) return;
    scene.target = withXY(scene.target, scene.handles, x, y);
    drawEditor();
    void poseGoal();
  }) : () => undefined;

  // where the model and the goal are on screen (for people's tests and automated ones alike):
  // data-screen-model and data-screen-goal = "x,y,on" in CSS pixels of the view
  const marks = viewer
    ? [viewer.mark('model', () => scene?.model.root ?? null), viewer.mark('goal', () => (scene?.goal.visible ? scene.goal.root : null))]
    : [];
  // the drop lines follow the model and the goal (dragged, typed); the view redraws when they move
  let placed = '';
  const stopDrops = viewer
    ? viewer.onBeforeRender(() => {
        const s = scene;
        const m = s?.model.root;
        const g = s?.goal.root;
        if (!s || !m || !g) return;
        const off = s.goal.group.position;
        const key = [m.position.x, m.position.y, m.position.z, g.position.x + off.x, g.position.y + off.y, g.position.z, viewer.groundZ].map((v) => v.toFixed(3)).join();
        if (key === placed) return;
        placed = key;
        s.drops[0].set(m.position.x, m.position.y, m.position.z, viewer.groundZ);
        s.drops[1].set(g.position.x + off.x, g.position.y + off.y, g.position.z, viewer.groundZ);
        viewer.invalidate();
      })
    : () => undefined;

  // ---------------------------------------------------------------- the job
  const stopJob = (): void => {
    if (!job) return;
    job.events?.close();
    window.clearInterval(job.poll);
    cancelBtn.disabled = true;
    clearNotice('job-queued');
  };

  /** Forget the job shown (another task was chosen): its events, status, curve and replay. */
  const clearJob = (): void => {
    stopJob();
    job = null;
    replay?.dispose();
    replay = null;
    plot.set([]);
    jobStatus.textContent = 'No job yet.';
    delete jobStatus.dataset.status;
    delete jobStatus.dataset.job;
    delete jobStatus.dataset.successPhysics;
    delete jobStatus.dataset.verdict;
    clearNotice('job');
  };

  const showProgress = (): void => {
    if (!job) return;
    const pts = job.points;
    plot.set([
      { name: 'objective', xs: pts.map((p) => p.iteration), ys: pts.map((p) => p.objective ?? NaN), color: '#4fc3f7' },
      { name: 'best', xs: pts.map((p) => p.iteration), ys: pts.map((p) => p.best_objective ?? NaN), color: '#aed581' },
    ]);
    plot.el.dataset.objectives = JSON.stringify(pts.map((p) => p.objective ?? null));
  };

  const finish = async (status: JobStatus): Promise<void> => {
    stopJob();
    jobStatus.dataset.status = status.status;
    if (status.status === 'failed') {
      jobStatus.textContent = `Job ${status.id} failed.`;
      notify(`The controller job failed: ${status.error ?? 'no reason was given'}.`, 'error', 'job');
      return;
    }
    if (status.status === 'cancelled') {
      jobStatus.textContent = `Job ${status.id} was cancelled.`;
      return;
    }
    const ran = `Job ${status.id} ran ${status.iteration} iterations (best objective ${fmt(status.best_objective)}).`;
    jobStatus.textContent = `${ran} Loading its result…`;
    const j = job;
    try {
      const result: JobResult = await ctx.controller.result(status.id);
      const s = scene;
      if (!alive || !s || job !== j) return;
      // the verdict is the result's own (success_physics, success_emulator): never judged again here
      jobStatus.textContent = `${ran} ${outcomeSummary(result)}`;
      jobStatus.dataset.successPhysics = String(result.success_physics ?? '');
      jobStatus.dataset.verdict = verdictOf(result);
      replay?.dispose();
      replay = new Replay(ctx.emulator, s.geometry, s.detail.layout, result, s.detail.super_timestep);
      replayHost.append(replay.el);
      await replay.start();
    } catch (e) {
      notify(`The job ended but its result could not be shown. ${errorText(e)}`, 'error', 'job');
    }
  };

  const poll = async (): Promise<void> => {
    const j = job;
    if (!j) return;
    let st: JobStatus;
    try {
      st = await ctx.controller.job(j.id);
      clearNotice('job-lost');
    } catch (e) {
      notify(`Lost contact with the controller service while following job ${j.id}. ${errorText(e)}`, 'error', 'job-lost');
      return;
    }
    if (job !== j) return;
    jobStatus.dataset.status = st.status;
    if (st.status === 'queued') {
      const waited = (performance.now() - j.queuedSince) / 1000;
      jobStatus.textContent = `Job ${j.id} is queued (${waited.toFixed(0)} s).`;
      if (waited > QUEUED_WARN_S)
        notify(
          `Job ${j.id} has waited ${waited.toFixed(0)} s and no controller worker has started it. Is a worker running? ` +
            '(make up starts one; by hand: python -m services.controller.worker)',
          'warning',
          'job-queued',
        );
    } else {
      j.queuedSince = performance.now();
      clearNotice('job-queued');
    }
    if (st.status === 'running') {
      jobStatus.textContent = `Job ${j.id} is running: iteration ${st.iteration}${st.max_iterations ? ` of at most ${st.max_iterations}` : ''}, best objective ${fmt(st.best_objective)}.`;
      const history = st.objective_history ?? [];
      if (history.length > j.points.length) {
        j.points = history.map((o, i) => ({ iteration: i + 1, objective: o, best_objective: null }));
        let best = Infinity;
        for (const p of j.points) {
          if (p.objective !== null && p.objective !== undefined && p.objective < best) best = p.objective;
          p.best_objective = Number.isFinite(best) ? best : null;
        }
        showProgress();
      }
    }
    if (FINAL_STATES.includes(st.status)) await finish(st);
  };

  const submit = async (): Promise<void> => {
    const s = scene;
    if (!s) return;
    stopJob();
    replay?.dispose();
    replay = null;
    clearNotice('job');
    submitBtn.disabled = true;
    jobStatus.textContent = 'Submitting…';
    try {
      const accepted = await ctx.controller.submit({
        task: s.task.name,
        target_state: s.target,
        idempotency_key: `dash-${Date.now().toString(36)}-${Math.random().toString(36).slice(2, 10)}`,
      });
      const j = { id: accepted.id, events: null as EventSource | null, poll: 0, queuedSince: performance.now(), points: [] as ProgressEvent[] };
      job = j;
      jobStatus.textContent = `Job ${j.id} is ${accepted.status}.`;
      jobStatus.dataset.status = accepted.status;
      jobStatus.dataset.job = j.id;
      cancelBtn.disabled = false;
      showProgress();
      const es = ctx.controller.events(j.id);
      j.events = es;
      es.addEventListener('progress', (ev) => {
        if (job !== j) return;
        const p = JSON.parse((ev as MessageEvent<string>).data) as ProgressEvent;
        if (j.points.some((q) => q.iteration === p.iteration)) return;
        j.points.push(p);
        j.points.sort((a, b) => a.iteration - b.iteration);
        showProgress();
      });
      es.addEventListener('end', () => {
        es.close();
        void poll();
      });
      es.onerror = () => {
        if (es.readyState === EventSource.CLOSED) j.events = null;
      };
      j.poll = window.setInterval(() => void poll(), POLL_MS);
    } catch (e) {
      jobStatus.textContent = 'The job was not submitted.';
      notify(`Could not submit the job. ${errorText(e)}`, 'error', 'job');
    } finally {
      submitBtn.disabled = false;
    }
  };
  submitBtn.addEventListener('click', () => void submit());
  cancelBtn.addEventListener('click', () => {
    if (!job) return;
    ctx.controller.cancel(job.id).catch((e: unknown) => notify(`Could not cancel the job. ${errorText(e)}`, 'error', 'job'));
  });

  void (async () => {
    try {
      tasks = await ctx.controller.tasks();
      if (!alive) return;
      taskSelect.append(...tasks.map((t) => h('option', { value: t.name }, `${t.name}${t.model ? ` (${t.model})` : ''}`)));
      const want = new URLSearchParams(location.hash.split('?')[1] ?? '').get('task');
      const pick = defaultTask(tasks, want);
      if (pick) {
        taskSelect.value = pick.name;
        await selectTask(pick.name);
      } else desc.textContent = 'The controller service offers no tasks.';
    } catch (e) {
      desc.textContent = 'No tasks: the controller service did not answer.';
      notify(`Cannot list the controller tasks. ${errorText(e)}`, 'error', 'controller');
    }
  })();

  return () => {
    alive = false;
    stopJob();
    drag();
    marks.forEach((m) => m());
    replay?.dispose();
    stopDrops();
    if (scene) disposeScene(scene);
    viewer?.dispose();
  };
};

function disposeScene(s: Scene): void {
  s.model.dispose();
  s.goal.dispose();
  s.drops.forEach((d) => d.dispose());
}

/** Pointer drag of the goal on the horizontal plane through it; calls `moved(x, y)` on release. */
function dragGoal(viewer: Viewer, current: () => Scene | null, moved: (x: number, y: number) => void): () => void {
  const canvas = viewer.renderer.domElement;
  const ray = new THREE.Raycaster();
  let active: { start: THREE.Vector3; x0: number; y0: number; plane: THREE.Plane } | null = null;

  const rayAt = (ev: PointerEvent): THREE.Ray => {
    const r = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1);
    ray.setFromCamera(ndc, viewer.camera);
    // into MuJoCo's frame (the `world` group), where the ground is z = const
    const inv = viewer.world.matrixWorld.clone().invert();
    return ray.ray.clone().applyMatrix4(inv);
  };

  const down = (ev: PointerEvent): void => {
    const s = current();
    if (!s || !s.handles.xy || ev.button !== 0) return;
    const r = canvas.getBoundingClientRect();
    ray.setFromCamera(new THREE.Vector2(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1), viewer.camera);
    if (!ray.intersectObject(s.goal.group, true).length) return;
    const root = s.goal.bodies[0];
    const z = root ? root.position.z : 0;
    const plane = new THREE.Plane(new THREE.Vector3(0, 0, 1), -z);
    const start = rayAt(ev).intersectPlane(plane, new THREE.Vector3());
    if (!start) return;
    const [ix, iy] = s.handles.xy;
    active = { start, x0: s.target[ix] ?? 0, y0: s.target[iy] ?? 0, plane };
    viewer.controls.enabled = false;
    canvas.setPointerCapture(ev.pointerId);
    canvas.classList.add('dragging');
    ev.preventDefault();
  };
  const move = (ev: PointerEvent): void => {
    const s = current();
    if (!active || !s) return;
    const p = rayAt(ev).intersectPlane(active.plane, new THREE.Vector3());
    if (!p) return;
    s.goal.group.position.set(p.x - active.start.x, p.y - active.start.y, 0);
  };
  const up = (ev: PointerEvent): void => {
    const s = current();
    if (!active) return;
    const a = active;
    active = null;
    viewer.controls.enabled = true;
    canvas.classList.remove('dragging');
    if (canvas.hasPointerCapture(ev.pointerId)) canvas.releasePointerCapture(ev.pointerId);
    if (!s) return;
    const off = s.goal.group.position;
    moved(a.x0 + off.x, a.y0 + off.y); // the offset is dropped when the new poses arrive
  };
  canvas.addEventListener('pointerdown', down);
  canvas.addEventListener('pointermove', move);
  canvas.addEventListener('pointerup', up);
  canvas.addEventListener('pointercancel', up);
  return () => {
    canvas.removeEventListener('pointerdown', down);
    canvas.removeEventListener('pointermove', move);
    canvas.removeEventListener('pointerup', up);
    canvas.removeEventListener('pointercancel', up);
  };
}
