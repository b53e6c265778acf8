// Playground: start a session of any model and drive it live (keyboard or sliders derived from the
// manifest's controls) over a real-time websocket; the view interpolates the states to the display
// rate. "MuJoCo ghost" shows the physics driven by the same controls, translucent.
import type { ModelDetail, ModelGeometry, SessionInfo } from '../api/emulator.gen';
import { errorText } from '../api/http';
import { ModelView } from '../scene/model';
import { makeViewer, staging } from '../scene/setup';
import type { Viewer } from '../scene/viewer';
import { bindingsFor, Drive, keyLabel } from '../session/inputs';
import { RealtimeSession } from '../session/realtime';
import { fmt, h } from '../ui/dom';
import { clearNotice, notify } from '../ui/notices';
import type { Ctx, Page } from './context';

interface Live {
  info: SessionInfo;
  detail: ModelDetail;
  geometry: ModelGeometry;
  socket: RealtimeSession;
  drive: Drive;
  model: ModelView;
  ghost: ModelView;
  stopFrame: () => void;
}

export const playgroundPage: Page = (root, ctx) => {
  const select = h('select', { id: 'pg-model', 'aria-label': 'model' });
  const startBtn = h('button', { id: 'pg-start', class: 'primary' }, 'Start session');
  const stopBtn = h('button', { id: 'pg-stop', disabled: true }, 'Stop');
  const ghostBox = h('input', { type: 'checkbox', id: 'pg-ghost' });
  const sliders = h('div', { class: 'sliders', id: 'pg-sliders' });
  const status = h('div', { class: 'status', id: 'pg-status' }, 'No session. Pick a model and start one.');
  const viewHost = h('div', { class: 'view', id: 'pg-view' });
  root.append(
    h('h1', {}, 'Playground'),
    h(
      'div',
      { class: 'split' },
      h(
        'aside',
        { class: 'panel' },
        h('label', {}, 'Model ', select),
        h('div', { class: 'buttons' }, startBtn, stopBtn),
        h('label', { class: 'check' }, ghostBox, ' Show the MuJoCo ghost (same controls)'),
        sliders,
        status,
      ),
      viewHost,
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
    l.stopFrame();
    l.socket.close();
    l.model.dispose();
    l.ghost.dispose();
    sliders.textContent = '';
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
      const info = await ctx.emulator.createSession({ model: name });
      if (!alive) return;
      live = begin(ctx, viewer, info, detail, geometry, ghostBox.checked, sliders, status, () => void stop());
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
  });
  const onKey = (ev: KeyboardEvent): void => {
    if (!live || (ev.target instanceof HTMLInputElement && ev.target.type !== 'range') || ev.target instanceof HTMLSelectElement) return;
    const used = ev.type === 'keydown' ? live.drive.press(ev.code) : live.drive.release(ev.code);
    if (used) ev.preventDefault();
  };
  const onBlur = (): void => live?.drive.releaseAll();
  window.addEventListener('keydown', onKey);
  window.addEventListener('keyup', onKey);
  window.addEventListener('blur', onBlur);

  void (async () => {
    try {
      const { models } = await ctx.emulator.models();
      select.append(...models.map((m) => h('option', { value: m.model }, m.model)));
      // the model the URL asks for, else the first one the emulator service lists
      const want = new URLSearchParams(location.hash.split('?')[1] ?? '').get('model');
      const pick = models.find((m) => m.model === want) ?? models[0];
      if (pick) select.value = pick.model;
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
    viewer?.dispose();
  };
};

function begin(
  ctx: Ctx,
  viewer: Viewer | null,
  info: SessionInfo,
  detail: ModelDetail,
  geometry: ModelGeometry,
  ghostOn: boolean,
  sliders: HTMLElement,
  status: HTMLElement,
  onDead: () => void,
): Live {
  const drive = new Drive(bindingsFor(detail.controls));
  const model = new ModelView(geometry);
  const ghost = new ModelView(geometry, { ghost: true, color: 0x9be7ff, opacity: 0.3 });
  ghost.visible = ghostOn;
  const socket = new RealtimeSession(ctx.emulator.socketUrl(info.id, `mode=realtime&poses=true${ghostOn ? '&shadow=true' : ''}`), {
    onError: (text, code) => {
      notify(text, 'error', 'playground');
      if (code === 'diverged' || code === 'unknown_session') onDead();
    },
    onClose: (text) => {
      notify(text, 'error', 'playground');
      onDead();
    },
  });
  const valueLabels: HTMLElement[] = [];
  sliders.textContent = '';
  if (!drive.bindings.length) sliders.append(h('p', { class: 'muted' }, 'This model has no controls: watch it move.'));
  drive.bindings.forEach((b, i) => {
    const value = h('span', { class: 'value' }, fmt(b.rest));
    valueLabels.push(value);
    const range = h('input', { type: 'range', min: b.low, max: b.high, step: (b.high - b.low) / 200, value: b.rest, 'data-control': b.name });
    range.addEventListener('input', () => {
      drive.base[i] = Number(range.value);
    });
    const keys = b.keyHigh ? h('span', { class: 'keys' }, `${keyLabel(b.keyHigh)} / ${keyLabel(b.keyLow)}`) : null;
    sliders.append(h('div', { class: 'slider' }, h('div', { class: 'slider-head' }, h('b', {}, b.name), ' ', value, ' ', keys), range));
  });
  if (viewer) {
    viewer.world.add(model.group, ghost.group);
    const st = staging(geometry);
    viewer.setGroundHeight(st.ground);
    viewer.frame(st.center, st.radius);
  }
  let lastStatus = 0;
  const stopFrame = viewer
    ? viewer.onBeforeRender((now) => {
        const u = drive.values();
        socket.setControls(u);
        const poses = socket.sample(now);
        if (poses) {
          model.setPoses(poses);
          viewer.follow(poses[0] ?? null);
        }
        const shadow = ghost.group.visible ? socket.sample(now, socket.shadow) : null;
        if (shadow) ghost.setPoses(shadow);
        if (now - lastStatus > 200) {
          lastStatus = now;
          u.forEach((v, i) => {
            const label = valueLabels[i];
            if (label) label.textContent = fmt(v);
          });
          const s = socket.last;
          const fps = window.__neuro?.fps ?? 0;
          status.textContent = s
            ? `session ${info.id} · t = ${s.t.toFixed(1)} s · ${s.steps} super-steps of ${fmt(detail.super_timestep)} s${s.clipped ? ' · controls clipped to the trained range' : ''} · ${fps.toFixed(0)} fps`
            : `session ${info.id} · waiting for the first state…`;
        }
      })
    : () => undefined;
  return { info, detail, geometry, socket, drive, model, ghost, stopFrame };
}
