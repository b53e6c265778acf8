// The dashboard: hash routes #/models, #/playground, #/controllers, #/policies; a health line for the services (the
// trainer's too when there is one);
// every error reaches the person as a notice in plain words.
import './style.css';
import { ControllerApi } from './api/controller';
import { EmulatorApi } from './api/emulator';
import { TrainerApi } from './api/trainer';
import { errorText } from './api/http';
import { loadConfig } from './config';
import type { Ctx, Page } from './pages/context';
import { controllersPage } from './pages/controllers';
import { modelsPage } from './pages/models';
import { playgroundPage } from './pages/playground';
import { policiesPage } from './pages/policies';
import { pinFullResolution } from './scene/loop';
import { h } from './ui/dom';
import { keyControl } from './ui/keycontrol';
import { clearAll, clearNotice, initNotices, notify } from './ui/notices';

const PAGES: Record<string, { title: string; page: Page }> = {
  models: { title: 'Models', page: modelsPage },
  playground: { title: 'Playground', page: playgroundPage },
  controllers: { title: 'Controllers', page: controllersPage },
  policies: { title: 'Policies', page: policiesPage },
};

function byId(id: string): HTMLElement {
  const el = document.getElementById(id);
  if (!el) throw new Error(`the page has no #${id}`);
  return el;
}

function route(): string {
  const name = location.hash.replace(/^#\/?/, '').split('?')[0] ?? '';
  return name in PAGES ? name : 'models';
}

async function watchHealth(ctx: Ctx, el: HTMLElement): Promise<void> {
  const trainer = ctx.trainer;
  const checks: [string, () => Promise<unknown>, string][] = [
    ['emulator', () => ctx.emulator.ready(), ctx.emulator.base],
    ['controller', () => ctx.controller.ready(), ctx.controller.base],
    ...(trainer ? [['trainer', () => trainer.ready(), trainer.base] as [string, () => Promise<unknown>, string]] : []),
  ];
  const dots = checks.map(([name]) => h('span', { class: 'dot', 'data-service': name }, name));
  el.append(...dots);
  const check = async (): Promise<void> => {
    await Promise.all(
      checks.map(async ([name, call, base], i) => {
        const dot = dots[i]!;
        try {
          await call();
          dot.className = 'dot up';
          dot.title = `${name}: ready (${base})`;
          clearNotice(`down-${name}`);
        } catch (e) {
          dot.className = 'dot down';
          dot.title = `${name}: ${errorText(e)}`;
          notify(errorText(e), 'error', `down-${name}`);
        }
      }),
    );
  };
  await check();
  window.setInterval(() => void check(), 5000);
}

async function main(): Promise<void> {
  initNotices(byId('notices'));
  window.addEventListener('error', (ev) => notify(`Something went wrong in the dashboard: ${ev.message}`));
  window.addEventListener('unhandledrejection', (ev) => notify(`Something went wrong in the dashboard: ${errorText(ev.reason)}`));
  const { config, warning } = await loadConfig(location.href);
  if (warning) notify(warning, 'warning');
  const ctx: Ctx = {
    emulator: new EmulatorApi(config.emulatorUrl),
    controller: new ControllerApi(config.controllerUrl),
    trainer: config.trainerUrl ? new TrainerApi(config.trainerUrl) : null,
  };
  const nav = byId('nav');
  const links = Object.entries(PAGES).map(([key, p]) => h('a', { href: `#/${key}`, 'data-page': key }, p.title));
  nav.append(...links);
  const pageHost = byId('page');
  let teardown: (() => void) | null = null;
  const show = (): void => {
    teardown?.();
    pinFullResolution(new URLSearchParams(location.hash.split('?')[1] ?? '').get('resolution') === 'full');
    pageHost.textContent = '';
    const name = route();
    links.forEach((a) => a.classList.toggle('active', a.dataset.page === name));
    const root = h('div', { class: `page page-${name}`, 'data-page': name });
    pageHost.append(root);
    document.title = `${PAGES[name]!.title} · NeuroAnimator`;
    teardown = PAGES[name]!.page(root, ctx);
  };
  window.addEventListener('hashchange', show);
  show();
  keyControl(byId('key'), () => {
    clearAll();
    show();
  });
  void watchHealth(ctx, byId('health'));
}

void main();
