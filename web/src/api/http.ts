// fetch with errors a person can read: every failure becomes a ServiceError whose message names the
// service and says what went wrong in plain words.
import { withKeyHeader } from './key';

export class ServiceError extends Error {
  /** `detail`: the service's own message, when it sent one. */
  constructor(
    message: string,
    readonly service: string,
    readonly status: number | null,
    readonly code: string | null = null,
    readonly detail: string | null = null,
  ) {
    super(message);
    this.name = 'ServiceError';
  }
}

/** The message of a failed call: the service's own message when it sent one (JSON `message`). */
export function describeFailure(service: string, status: number, statusText: string, body: unknown): ServiceError {
  let code: string | null = null;
  let detail: string | null = null;
  if (body && typeof body === 'object') {
    const b = body as Record<string, unknown>;
    if (typeof b.error === 'string') code = b.error;
    if (typeof b.message === 'string') detail = b.message;
    else if (typeof b.detail === 'string') detail = b.detail;
  } else if (typeof body === 'string' && body.trim() && body.length < 300) {
    detail = body.trim();
  }
  let text = detail
    ? `The ${service} service refused the request: ${detail}`
    : `The ${service} service answered ${status}${statusText ? ` ${statusText}` : ''}.`;
  if (status === 401) text = `${text.replace(/[.\s]*$/, '')}. Enter your API key with the key button at the top right.`;
  return new ServiceError(text, service, status, code, detail);
}

export function unreachable(service: string, base: string): ServiceError {
  return new ServiceError(
    `The ${service} service is not reachable at ${base}. Is it running? (make up starts it.)`,
    service,
    null,
    'unreachable',
  );
}

/** A response's body: its JSON, else its text (null when empty). */
async function bodyOf(r: Response): Promise<unknown> {
  const text = await r.text();
  try {
    return text ? JSON.parse(text) : null;
  } catch {
    return text;
  }
}

/** fetch, with the person's API key (key.ts) and "not reachable" in plain words when the service does
 * not answer. */
export async function send(service: string, base: string, path: string, init?: RequestInit): Promise<Response> {
  try {
    return await fetch(base + path, { ...init, headers: withKeyHeader(init?.headers) });
  } catch {
    throw unreachable(service, base);
  }
}

/** The JSON body of a successful response; a `ServiceError` with the service's message otherwise. */
export async function jsonOf<T>(service: string, r: Response): Promise<T> {
  const body = await bodyOf(r);
  if (!r.ok) throw describeFailure(service, r.status, r.statusText, body);
  return body as T;
}

export async function requestJson<T>(service: string, base: string, path: string, init?: RequestInit): Promise<T> {
  const headers = new Headers(init?.headers);
  headers.set('Accept', 'application/json');
  if (init?.body && !headers.has('Content-Type')) headers.set('Content-Type', 'application/json');
  const r = await send(service, base, path, { ...init, headers });
  return jsonOf<T>(service, r);
}

/** A file's bytes (a mesh, a texture). */
export async function requestBytes(service: string, base: string, path: string): Promise<ArrayBuffer> {
  const r = await send(service, base, path);
  if (!r.ok) throw describeFailure(service, r.status, r.statusText, await bodyOf(r));
  return r.arrayBuffer();
}

export function errorText(e: unknown): string {
  if (e instanceof Error) return e.message;
  return String(e);
}
