// Playground: start a session of any model and drive it live (keyboard or sliders derived from the
// manifest's controls and external forces) over a real-time websocket; the view interpolates the
// states to the display rate, keeps the model framed with the ground below it, and draws its trail.
// "MuJoCo ghost" shows the physics driven by the same inputs as a cyan outline, with the gap between
// the two (root position, attitude) as numbers and a curve beside the view.
import * as THREE from 'three';
import type { ControlInfo, DriverInfo, ForceInfo, ModelDetail, ModelGeometry, SessionInfo, WsState } from '../api/emulator.gen';
import { errorText } from '../api/http';
import { gapLabel, poseGap, rootMoves } from '../scene/divergence';
import type { Pose } from '../scene/interp';
import { groundHeight, ModelView, type MeshesDrawn } from '../scene/model';
import { makeViewer, meshFilesOf } from '../scene/setup';
import { DropLine, Trail } from '../scene/trail';
import type { Viewer } from '../scene/viewer';
import { bindingsFor, controlMeaning, Drive, keyLabel, restValue } from '../session/inputs';
import { envelopeText, RealtimeSession } from '../session/realtime';
import { holdControls } from '../session/hover';
import { driveNow, restState, startFromQuery } from '../session/start';
import { fmt, h } from '../ui/dom';
import { clearNotice, notify } from '../ui/notices';
import { DivergencePanel, GHOST_COLOR, GHOST_LOOK, MODEL_TRAIL } from './divergence';
import type { Ctx, Page } from './context';

interface Live {
  info: SessionInfo;
  socket: RealtimeSession;
  drive: Drive;
  model: ModelView;
  ghost: ModelView;
  /** Sends the inputs as they are now (only what changed goes out). */
  send: () => void;
  dispose: () => void;
}

export const playgroundPage: Page = (root, ctx) => {
  const select = h('select', { id: 'pg-model', 'aria-label': 'model' });
  const startFrom = h(
    'select',
    { id: 'pg-start-from', 'aria-label': 'start from' },
    h('option', { value: 'rest' }, 'at rest, in its MJCF pose'),
    h('option', { value: 'random' }, 'a random typical state'),
  );
  // a model driven by its own controller (the runner) can start in its driven motion
  const drivenOption = h('option', { value: 'driver', hidden: true }, 'driven by its controller');
  const startBtn = h('button', { id: 'pg-start', class: 'primary' }, 'Start session');
  const stopBtn = h('button', { id: 'pg-stop', disabled: true }, 'Stop');
  const ghostBox = h('input', { type: 'checkbox', id: 'pg-ghost' });
  const sliders = h('div', { class: 'sliders', id: 'pg-sliders' });
  const status = h('div', { class: 'status', id: 'pg-status' }, 'No session. Pick a model and start one.');
  const envelope = h('div', { class: 'envelope', id: 'pg-envelope', hidden: true });
  const viewHost = h('div', { class: 'view', id: 'pg-view' });
  const divergence = new DivergencePanel('pg-divergence', { overlay: true });
  root.append(
    h('h1', {}, 'Playground'),
    h(
      'div',
      { class: 'split' },
      h(
        'aside',
        { class: 'panel' },
        h('label', {}, 'Model ', select),
        h('label', {}, 'Start ', startFrom),
        h('div', { class: 'buttons' }, startBtn, stopBtn),
        h('label', { class: 'check' }, ghostBox, ' Show the MuJoCo ghost (same inputs, or its own run of the controller)'),
        h(
          'p',
          { class: 'legend' },
          h('span', { class: 'swatch solid' }),
          'emulator ',
          h('span', { class: 'swatch ghost' }),
          'MuJoCo ghost ',
          h('span', { class: 'swatch trail' }),
          'trail',
        ),
        sliders,
        envelope,
        status,
      ),
      h('div', { class: 'stage' }, viewHost, divergence.el),
    ),
  );
  const viewer = makeViewer(viewHost);
  let live: Live | null = null;
  let alive = true;

  const stop = async (): Promise<void> => {
    const l = live;
    live = null;
    stopBtn.disabled = true;
    if (!l) return;
    l.dispose();
    sliders.textContent = '';
    envelope.hidden = true;
    envelope.textContent = ''; // the next session's first word on its envelope is news
    clearNotice('envelope');
    try {
      await ctx.emulator.deleteSession(l.info.id);
    } catch {
      /* expired or the service is gone: nothing to clean up */
    }
  };

  const start = async (): Promise<void> => {
    await stop();
    const name = select.value;
    if (!name) return;
    startBtn.disabled = true;
    status.textContent = `Starting a ${name} session…`;
    try {
      const [detail, geometry] = await Promise.all([ctx.emulator.model(name), ctx.emulator.geometry(name)]);
      // at rest, or a random typical state (?seed=N in the page's address: the same one every time)
      // the service's rest state (MuJoCo's qpos0); from the layout only for a service that does not send it
      const rest = startFrom.value === 'rest' ? (geometry.rest_state ?? restState(detail.layout, geometry.rest_poses[0])) : null;
      const { seed } = startFromQuery(location.hash.split('?')[1] ?? '');
      const driven = startFrom.value === 'driver' && detail.driver;
      // a model that falls at rest (the lander 20 m above its pad) starts with the controls that hold
      // it still, measured before its session starts so that it does not fall meanwhile
      const hold = driven ? null : await hoverControls(ctx, detail, geometry.rest_state ?? restState(detail.layout, geometry.rest_poses[0]));
      if (!alive) return;
      const info = await ctx.emulator.createSession(
        driven ? { model: name, driver: {} } : rest ? { model: name, state: rest } : seed !== null ? { model: name, seed } : { model: name },
      );
      if (!alive) return;
      live = begin(ctx, viewer, { info, detail, geometry, hold, ghostOn: ghostBox.checked, sliders, status, envelope, divergence }, () => void stop());
      stopBtn.disabled = false;
      clearNotice('playground');
    } catch (e) {
      status.textContent = 'No session.';
      notify(`Could not start a ${name} session. ${errorText(e)}`, 'error', 'playground');
    } finally {
      startBtn.disabled = false;
    }
  };

  startBtn.addEventListener('click', () => void start());
  stopBtn.addEventListener('click', () => {
    void stop();
    status.textContent = 'Session stopped.';
  });
  ghostBox.addEventListener('change', () => {
    if (!live) return;
    live.socket.setShadow(ghostBox.checked);
    live.ghost.visible = ghostBox.checked;
    divergence.reset(ghostBox.checked);
  });
  // keys drive the session unless they are typing into a field: a ticked checkbox or a moved slider
  // keeps the focus, and driving must go on
  const typing = (t: EventTarget | null): boolean =>
    (t instanceof HTMLInputElement && !['range', 'checkbox', 'radio', 'button'].includes(t.type)) ||
    t instanceof HTMLSelectElement ||
    t instanceof HTMLTextAreaElement;
  const onKey = (ev: KeyboardEvent): void => {
    if (!live || typing(ev.target)) return;
    const used = ev.type === 'keydown' ? live.drive.press(ev.code) : live.drive.release(ev.code);
    if (!used) return;
    ev.preventDefault();
    live.send();
  };
  const onBlur = (): void => {
    live?.drive.releaseAll();
    live?.send();
  };
  window.addEventListener('keydown', onKey);
  window.addEventListener('keyup', onKey);
  window.addEventListener('blur', onBlur);

  void (async () => {
    try {
      const { models } = await ctx.emulator.models();
      select.append(...models.map((m) => h('option', { value: m.model }, m.model)));
      // the model the URL asks for, else the first one the emulator service lists
      const query = location.hash.split('?')[1] ?? '';
      const want = new URLSearchParams(query).get('model');
      // a model without inputs starts moving (a random state); one a person drives starts at rest
      const asked = startFromQuery(query).from;
      const pick = models.find((m) => m.model === want) ?? models[0];
      if (pick) select.value = pick.model;
      startFrom.append(drivenOption);
      const pickStart = (): void => {
        const m = models.find((x) => x.model === select.value);
        const name = select.value;
        // the address's start is for the address's model; another one starts as its inputs suggest
        const given = name === want ? asked : null;
        drivenOption.hidden = true;
        startFrom.value = given ?? (m && m.num_controls + m.num_forces > 0 ? 'rest' : 'random');
        // a model with a driver starts driven unless the address says otherwise
        void ctx.emulator
          .model(name)
          .then((d) => {
            if (!d.driver || select.value !== name) return;
            drivenOption.hidden = false;
            drivenOption.textContent = `driven by its controller (${d.driver.name})`;
            if (!given || given === 'driver') startFrom.value = 'driver';
          })
          .catch(() => undefined);
      };
      pickStart();
      select.addEventListener('change', pickStart);
      // "Drive it" (a model just trained): its session starts at once
      if (driveNow(query) && pick?.model === want && alive) void start();
    } catch (e) {
      notify(`Cannot list the models. ${errorText(e)}`, 'error', 'playground');
    }
  })();

  return () => {
    alive = false;
    window.removeEventListener('keydown', onKey);
    window.removeEventListener('keyup', onKey);
    window.removeEventListener('blur', onBlur);
    void stop();
    divergence.dispose();
    viewer?.dispose();
  };
};

/** The controls that hold a falling model still at its rest state (session/hover.ts), measured on
 * sessions of its own that are ended at once; null when it does not fall or the measure fails (it then
 * starts with its controls at rest, as any other model). */
async function hoverControls(ctx: Ctx, detail: ModelDetail, rest: number[] | null): Promise<number[] | null> {
  if (!rest || !detail.controls.length) return null;
  // a model trained around an operating point (its keyframe, or the controls that hold it still) starts
  // with that point's controls: its emulator was trimmed to hold still there, as MuJoCo does
  const op = detail.operating;
  const held = op && (op.source === 'keyframe' || op.source === 'hold') ? op.control_centres?.[0] : undefined;
  if (held && held.length === detail.controls.length) return held;
  const base = detail.controls.map((c) => restValue(c.low, c.high));
  try {
    return await holdControls(detail.layout, detail.controls, base, detail.super_timestep, async (controls) => {
      const sessions = await Promise.all(controls.map(() => ctx.emulator.createSession({ model: detail.model, version: detail.version, state: rest })));
      try {
        const { results } = await ctx.emulator.stepBatch({ items: sessions.map((s, i) => ({ session: s.id, controls: controls[i] })) });
        return results.map((r) => r.state ?? []);
      } finally {
        for (const s of sessions) void ctx.emulator.deleteSession(s.id).catch(() => undefined);
      }
    });
  } catch {
    return null; // the session still starts, with its controls at rest
  }
}

interface Setup {
  info: SessionInfo;
  detail: ModelDetail;
  geometry: ModelGeometry;
  hold: number[] | null; // the controls that hold the model still, where it starts (null: at rest)
  ghostOn: boolean;
  sliders: HTMLElement;
  status: HTMLElement;
  envelope: HTMLElement;
  divergence: DivergencePanel;
}

/** Sliders for a driven session's driver parameters (the runner's target speed): they write `values`. */
function drawDriverSliders(host: HTMLElement, driver: DriverInfo, values: Record<string, number>): void {
  host.append(
    h('h3', {}, `Controller: ${driver.name}`),
    h('p', { class: 'meaning' }, `${(driver.description ?? '').replace(/\.?$/, '.')} It sets every control; the forces below are yours.`),
  );
  for (const p of driver.params) {
    const v = values[p.name] ?? p.default;
    const value = h('span', { class: 'value' }, `${fmt(v)} ${p.unit}`);
    const range = h('input', { type: 'range', min: p.low, max: p.high, step: (p.high - p.low) / 80, value: v, 'data-driver': p.name, 'aria-label': p.label });
    range.addEventListener('input', () => {
      values[p.name] = Number(range.value);
      value.textContent = `${fmt(values[p.name]!)} ${p.unit}`;
    });
    host.append(h('div', { class: 'slider' }, h('div', { class: 'slider-head' }, h('b', {}, p.label), ' ', value), range));
  }
}

/** Sliders for every control and force, with their keys and (as a tooltip) what they do. */
function drawSliders(host: HTMLElement, drive: Drive, controls: ControlInfo[], driven = false, forces: ForceInfo[] = []): HTMLElement[] {
  const labels: HTMLElement[] = [];
  if (!driven) host.textContent = '';
  if (!drive.bindings.length && !driven) host.append(h('p', { class: 'muted' }, 'This model has no inputs: watch it move.'));
  let kind = '';
  drive.bindings.forEach((b, i) => {
    if (b.kind !== kind) {
      kind = b.kind;
      if (b.kind === 'force') host.append(h('h3', {}, 'External forces'));
    }
    const value = h('span', { class: 'value' }, fmt(b.rest));
    labels.push(value);
    const range = h('input', { type: 'range', min: b.low, max: b.high, step: (b.high - b.low) / 200, value: b.rest, [`data-${b.kind}`]: b.name });
    range.addEventListener('input', () => {
      drive.base[i] = Number(range.value);
    });
    const keys = b.keyHigh ? h('span', { class: 'keys' }, `${keyLabel(b.keyHigh)} / ${keyLabel(b.keyLow)}`) : null;
    // what it applies under the name; the sign convention too when pointed at
    const control = b.kind === 'control' ? controls[b.index] : undefined;
    const force = b.kind === 'force' ? forces[b.index] : undefined;
    const short = control ? controlMeaning(control, false) : (force?.description ?? '');
    const long = control ? controlMeaning(control) : (force?.description ?? '');
    const unit = force?.unit ? h('span', { class: 'muted' }, ` ${force.unit}`) : null;
    const head = h('div', { class: 'slider-head' }, h('b', {}, b.name), ' ', value, unit, ' ', keys);
    const meaning = short ? h('div', { class: 'meaning', title: long }, short) : null;
    host.append(h('div', { class: 'slider', title: long }, head, meaning, range));
  });
  return labels;
}

/** Arrows for the external forces that push along a world axis (component 0–2 of a body's force). */
function forceArrows(viewer: Viewer, model: ModelView, forces: ForceInfo[]): (values: number[]) => void {
  const arrows = forces.map((f) => {
    const body = model.bodies.find((b) => b.name === f.body);
    const component = typeof f.component === 'number' ? f.component : -1;
    if (!body || component < 0 || component > 2) return null;
    const arrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.5, 0xff7043, 0.12, 0.08);
    arrow.visible = false;
    viewer.world.add(arrow);
    return { arrow, body, axis: component, scale: Math.max(Math.abs(f.low), Math.abs(f.high)) || 1 };
  });
  const at = new THREE.Vector3();
  return (values) => {
    arrows.forEach((a, i) => {
      if (!a) return;
      const v = values[i] ?? 0;
      a.arrow.visible = Math.abs(v) > 1e-6 && model.visible;
      if (!a.arrow.visible) return;
      // at the middle of the body's first geom (a link's centre), in MuJoCo's frame
      const geom = a.body.children[0];
      if (geom) geom.getWorldPosition(at);
      else a.body.getWorldPosition(at);
      viewer.world.worldToLocal(at);
      const dir = new THREE.Vector3().setComponent(a.axis, Math.sign(v));
      const length = 0.15 + 0.6 * (Math.abs(v) / a.scale);
      a.arrow.position.copy(at).addScaledVector(dir, -length); // the arrow pushes on the body
      a.arrow.setDirection(dir);
      a.arrow.setLength(length, 0.12, 0.08);
    });
  };
}

/** The mesh geoms drawn from their files, on the view (data-meshes: geom, file, triangles, colour), and
 * a warning naming those whose files could not be read (they stay boxes). */
function showMeshes(host: HTMLElement, model: string, m: MeshesDrawn): void {
  const colour = (o: THREE.Mesh): string | null => (o.material instanceof THREE.MeshStandardMaterial ? `#${o.material.color.getHexString(THREE.SRGBColorSpace)}` : null);
  host.dataset.meshes = JSON.stringify(
    m.drawn.map((o) => ({ geom: o.name, file: o.userData.meshFile, triangles: (o.geometry.getAttribute('position')?.count ?? 0) / 3, color: colour(o) })),
  );
  if (m.failed.length)
    notify(`Some meshes of ${model} are drawn as boxes: ${m.failed.map((f) => `${f.geom} (${f.reason})`).join('; ')}`, 'warning', 'meshes');
  else clearNotice('meshes');
}

function begin(ctx: Ctx, viewer: Viewer | null, s: Setup, onDead: () => void): Live {
  const { info, detail, geometry, divergence } = s;
  // a driven session: the model's controller sets the controls, the person its parameters and the forces
  const driver = info.driver && detail.driver ? detail.driver : null;
  const driverValues: Record<string, number> = { ...(info.driver ?? {}) };
  const hold = driver ? null : s.hold;
  const bindings = bindingsFor(driver ? [] : detail.controls, detail.forces).map((b) => (hold && b.kind === 'control' ? { ...b, rest: hold[b.index] ?? b.rest } : b));
  const drive = new Drive(bindings);
  const files = meshFilesOf(ctx.emulator, geometry);
  const model = new ModelView(geometry, {}, files);
  const ghost = new ModelView(geometry, GHOST_LOOK, files);
  ghost.visible = s.ghostOn;
  const rooted = rootMoves(detail.layout);
  divergence.configure(gapLabel(detail.layout), s.ghostOn);
  const onState = (msg: WsState): void => {
    if (msg.poses && msg.shadow?.poses && ghost.visible) {
      const gap = poseGap(msg.poses, msg.shadow.poses, rooted);
      if (gap) divergence.add(msg.t, gap);
    }
    const text = envelopeText(msg);
    if ((s.envelope.textContent ?? '') === (text ?? '')) return;
    // written only when it changes: a write is a repaint, and states come many times a second (and a
    // notice the person dismissed stays dismissed until the envelope says something new)
    s.envelope.hidden = !text;
    s.envelope.textContent = text ?? '';
    if (text) notify(`The session left the emulator's trained envelope: ${text}. Its states are extrapolated.`, 'warning', 'envelope');
    else clearNotice('envelope');
  };
  const socket = new RealtimeSession(ctx.emulator.socketUrl(info.id, `mode=realtime&poses=true${s.ghostOn ? '&shadow=true' : ''}`), {
    onState,
    onError: (text, code) => {
      notify(text, 'error', 'playground');
      if (code === 'diverged' || code === 'unknown_session') onDead();
    },
    onClose: (text) => {
      notify(text, 'error', 'playground');
      onDead();
    },
  });
  // the first inputs go as the socket opens, not with the first frame drawn: the server steps from the
  // moment it connects, and a page slow to draw (a busy machine, a hidden tab) let the lander fall
  // with its jet off until then, gaining a speed its hover thrust then kept; later ones as they change
  // (a key, a slider), not with the frames drawn: a page without WebGL draws none
  const send = (): void => {
    const { controls, forces } = drive.split();
    socket.setControls(controls, forces, driver ? driverValues : undefined);
  };
  send();
  s.sliders.textContent = '';
  s.sliders.addEventListener('input', send);
  if (driver) drawDriverSliders(s.sliders, driver, driverValues);
  const valueLabels = drawSliders(s.sliders, drive, detail.controls, !!driver, detail.forces);
  if (hold) {
    const held = detail.controls.map((c, i) => ({ c, v: hold[i] ?? 0 })).filter(({ c, v }) => v !== restValue(c.low, c.high));
    s.sliders.prepend(
      h('p', { class: 'meaning hold', id: 'pg-hold' }, `It falls with its controls at rest, so they start where they hold it still: ${held.map(({ c, v }) => `${c.name} ${fmt(v)}`).join(', ')}.`),
    );
  }
  const parts = { info, socket, drive, model, ghost, send };
  const close = (): void => {
    s.sliders.removeEventListener('input', send);
    socket.close();
  };
  if (!viewer) return { ...parts, dispose: close };
  const trail = new Trail(MODEL_TRAIL);
  const ghostTrail = new Trail(GHOST_COLOR);
  const drop = new DropLine(MODEL_TRAIL);
  drop.group.visible = rooted; // a free model's height above the ground; a fixed one stands on it
  viewer.world.add(model.group, ghost.group, trail.line, ghostTrail.line, drop.group);
  viewer.setGroundHeight(groundHeight(model, [geometry.rest_poses]));
  viewer.animating = true;
  // frame the moving bodies (a free model) or the whole model with its stand (a fixed one), with the
  // ghost while it is shown, and the ground below them while they are near it
  const framed = (): THREE.Box3 => viewer.boxOf(...(rooted ? model.moving : [model.group]), ...(ghost.visible ? ghost.moving : []));
  viewer.follow(framed);
  const arrows = forceArrows(viewer, model, detail.forces);
  // the spot on the ground below the model: data-screen-ground says whether the ground is in view
  const below = new THREE.Object3D();
  viewer.world.add(below);
  let meshes: MeshesDrawn | null = null;
  let over = false;
  // the skins drawn over the bodies (data-skins: name, vertices, triangles)
  viewer.host.dataset.skins = JSON.stringify(
    model.skins.map((k) => ({ skin: k.skin.name, vertices: k.skin.vertices.length / 3, triangles: k.skin.faces.length / 3 })),
  );
  void model.meshes.then((m) => {
    if (over) return;
    meshes = m;
    showMeshes(viewer.host, info.model, m);
    viewer.invalidate();
  });
  const unmark = [
    viewer.mark('model', () => model.root),
    viewer.mark('ghost', () => (ghost.visible ? ghost.root : null)),
    viewer.mark('ground', () => below),
    viewer.mark('mesh', () => meshes?.drawn[0] ?? null), // the first geom drawn from its mesh file
  ];
  let lastStatus = 0;
  const tracePoint = (poses: Pose[] | null, t: Trail): void => {
    const p = poses?.[rooted ? 0 : poses.length - 1];
    if (p) t.push(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0);
  };
  const stopFrame = viewer.onBeforeRender((now) => {
    const { controls, forces } = drive.split();
    arrows(forces);
    const poses = socket.sample(now);
    if (poses) {
      model.setPoses(poses);
      tracePoint(poses, trail);
      const p = poses[0];
      if (p) below.position.set(p[0] ?? 0, p[1] ?? 0, viewer.groundZ);
      if (p && rooted) drop.set(p[0] ?? 0, p[1] ?? 0, p[2] ?? 0, viewer.groundZ);
    }
    const shadow = ghost.visible ? socket.sample(now, socket.shadow) : null;
    if (shadow) {
      ghost.setPoses(shadow);
      tracePoint(shadow, ghostTrail);
    }
    ghostTrail.line.visible = ghost.visible;
    if (now - lastStatus > 200) {
      lastStatus = now;
      drive.values().forEach((v, i) => {
        const label = valueLabels[i];
        if (label) label.textContent = fmt(v);
      });
      const last = socket.last;
      const stats = window.__neuro;
      const fps = `${(stats?.fps ?? 0).toFixed(0)} fps${stats && stats.scale < 1 ? ` at ${Math.round(stats.scale * 100)} % resolution` : ''}`;
      s.status.dataset.sent = JSON.stringify(driver ? { controls, forces, driver: driverValues } : { controls, forces });
      s.status.dataset.t = String(last?.t ?? '');
      s.status.dataset.state = last ? JSON.stringify(last.state.map((v) => Number(v.toPrecision(4)))) : '';
      s.status.textContent = last
        ? `session ${info.id}${info.seed != null ? ` (start seed ${info.seed})` : ''} · t = ${last.t.toFixed(1)} s · ${last.steps} super-steps of ${fmt(detail.super_timestep)} s${driver ? ` · driven by its controller (${driver.name})` : ''}${last.clipped ? ' · inputs clipped to the trained range' : ''} · ${fps}`
        : `session ${info.id} · waiting for the first state…`;
    }
  });
  return {
    ...parts,
    dispose: () => {
      over = true;
      stopFrame();
      close();
      unmark.forEach((u) => u());
      viewer.follow(null);
      viewer.animating = false;
      model.dispose();
      ghost.dispose();
      trail.dispose();
      ghostTrail.dispose();
      below.removeFromParent();
      delete viewer.host.dataset.meshes;
      delete viewer.host.dataset.skins;
      drop.dispose();
      arrows([]);
      viewer.world.children.filter((c) => c instanceof THREE.ArrowHelper).forEach((c) => c.removeFromParent());
      divergence.reset(false);
      viewer.invalidate();
    },
  };
}
