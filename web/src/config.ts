// Where the services are: /config.json from the dashboard's server (python -m services.web), else the
// defaults of `make up`. URLs may be absolute or paths on the dashboard's own origin (behind a proxy).

export interface AppConfig {
  emulatorUrl: string;
  controllerUrl: string;
  /** null: the deployment has no trainer service (no "Add a model"). */
  trainerUrl: string | null;
}

export const DEFAULT_CONFIG: AppConfig = {
  emulatorUrl: 'http://127.0.0.1:8000',
  controllerUrl: 'http://127.0.0.1:8001',
  trainerUrl: 'http://127.0.0.1:8002',
};

/** An absolute http(s) URL for a service URL that may be a path on this page's origin. */
export function absolute(url: string, base: string): string {
  return new URL(url, base).toString().replace(/\/$/, '');
}

/** The websocket URL of `path` on the service at `httpUrl` (http → ws, https → wss). */
export function wsUrl(httpUrl: string, path: string, base: string): string {
  const u = new URL(absolute(httpUrl, base) + path);
  u.protocol = u.protocol === 'https:' ? 'wss:' : 'ws:';
  return u.toString();
}

export async function loadConfig(base: string): Promise<{ config: AppConfig; warning: string | null }> {
  try {
    const r = await fetch(new URL('config.json', base), { cache: 'no-store' });
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const raw = (await r.json()) as { emulator_url?: unknown; controller_url?: unknown; trainer_url?: unknown };
    const pick = (v: unknown, d: string): string => (typeof v === 'string' && v ? v : d);
    // the trainer: null or empty when the deployment has none; absent from an older server's config
    const trainer = raw.trainer_url === undefined ? DEFAULT_CONFIG.trainerUrl : typeof raw.trainer_url === 'string' && raw.trainer_url ? raw.trainer_url : null;
    return {
      config: {
        emulatorUrl: absolute(pick(raw.emulator_url, DEFAULT_CONFIG.emulatorUrl), base),
        controllerUrl: absolute(pick(raw.controller_url, DEFAULT_CONFIG.controllerUrl), base),
        trainerUrl: trainer === null ? null : absolute(trainer, base),
      },
      warning: null,
    };
  } catch (e) {
    return {
      config: DEFAULT_CONFIG,
      warning:
        `The dashboard's config.json could not be read (${String(e)}); ` +
        `using the default service addresses ${DEFAULT_CONFIG.emulatorUrl}, ${DEFAULT_CONFIG.controllerUrl} and ${DEFAULT_CONFIG.trainerUrl}.`,
    };
  }
}
