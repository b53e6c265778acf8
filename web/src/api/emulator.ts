// The emulator service's REST calls and websocket URL (types generated from proto/ in emulator.gen.ts).
import { wsUrl } from '../config';
import type {
  BatchStepRequest,
  BatchStepResponse,
  ModelDetail,
  ModelGeometry,
  ModelList,
  PosesResponse,
  SessionCreate,
  SessionInfo,
} from './emulator.gen';
import { requestBytes, requestJson } from './http';
import { withKeyQuery } from './key';

const versionQuery = (version?: string): string => (version ? `?version=${encodeURIComponent(version)}` : '');

export class EmulatorApi {
  constructor(readonly base: string) {}

  private get<T>(path: string): Promise<T> {
    return requestJson<T>('emulator', this.base, path);
  }

  private post<T>(path: string, body: unknown): Promise<T> {
    return requestJson<T>('emulator', this.base, path, { method: 'POST', body: JSON.stringify(body) });
  }

  ready(): Promise<{ status: string }> {
    return this.get('/readyz');
  }

  models(): Promise<ModelList> {
    return this.get('/models');
  }

  /** A model's manifest: its latest version's, or `version`'s. */
  model(name: string, version?: string): Promise<ModelDetail> {
    return this.get(`/models/${encodeURIComponent(name)}${versionQuery(version)}`);
  }

  geometry(name: string, version?: string): Promise<ModelGeometry> {
    return this.get(`/models/${encodeURIComponent(name)}/geometry${versionQuery(version)}`);
  }

  /** A file the model's MJCF names (a mesh: /geometry names it), as stored in its artifact. */
  asset(name: string, asset: string, version?: string): Promise<ArrayBuffer> {
    const query = version ? `?version=${encodeURIComponent(version)}` : '';
    return requestBytes('emulator', this.base, `/models/${encodeURIComponent(name)}/assets/${encodeURIComponent(asset)}${query}`);
  }

  poses(name: string, states: number[][], version?: string): Promise<PosesResponse> {
    return this.post(`/models/${encodeURIComponent(name)}/poses`, version ? { states, version } : { states });
  }

  createSession(req: SessionCreate): Promise<SessionInfo> {
    return this.post('/sessions', req);
  }

  /** One super-step of many sessions (POST /step): a result per item, in order. */
  stepBatch(req: BatchStepRequest): Promise<BatchStepResponse> {
    return this.post('/step', req);
  }

  async deleteSession(id: string): Promise<void> {
    await requestJson('emulator', this.base, `/sessions/${encodeURIComponent(id)}`, { method: 'DELETE' });
  }

  socketUrl(id: string, query: string): string {
    return withKeyQuery(wsUrl(this.base, `/ws/sessions/${encodeURIComponent(id)}?${query}`, location.href));
  }
}
