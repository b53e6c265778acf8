// fetch with errors a person can read: every failure becomes a ServiceError whose message names the
// service and says what went wrong in plain words.

export class ServiceError extends Error {
  constructor(
    message: string,
    readonly service: string,
    readonly status: number | null,
    readonly code: string | null = null,
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
  const text = detail
    ? `The ${service} service refused the request: ${detail}`
    : `The ${service} service answered ${status}${statusText ? ` ${statusText}` : ''}.`;
  return new ServiceError(text, service, status, code);
}

export function unreachable(service: string, base: string): ServiceError {
  return new ServiceError(
    `The ${service} service is not reachable at ${base}. Is it running? (make up starts it.)`,
    service,
    null,
    'unreachable',
  );
}

export async function requestJson<T>(service: string, base: string, path: string, init?: RequestInit): Promise<T> {
  let r: Response;
  try {
    r = await fetch(base + path, {
      ...init,
      headers: { Accept: 'application/json', ...(init?.body ? { 'Content-Type': 'application/json' } : {}) },
    });
  } catch {
    throw unreachable(service, base);
  }
  const text = await r.text();
  let body: unknown = null;
  try {
    body = text ? JSON.parse(text) : null;
  } catch {
    body = text;
  }
  if (!r.ok) throw describeFailure(service, r.status, r.statusText, body);
  return body as T;
}

export function errorText(e: unknown): string {
  if (e instanceof Error) return e.message;
  return String(e);
}
