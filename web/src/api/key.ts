// The API key the dashboard sends, when the services ask for one (API_KEYS set on the server). It is the
// person's own key: kept in this browser's localStorage, never in the page's address or the build.
// HTTP calls send it as `Authorization: Bearer <key>`; websockets and server-sent events, which a browser
// cannot give headers, as the `api_key` query parameter (the services accept it there and redact it from
// their logs).

const STORAGE = 'neuroanimator.apiKey';
let memory: string | null = null; // where localStorage is unavailable (a sandboxed frame)

export function apiKey(): string | null {
  try {
    return window.localStorage.getItem(STORAGE) || null;
  } catch {
    return memory;
  }
}

/** Remember `key` for the next calls (null or blank: forget it). */
export function setApiKey(key: string | null): void {
  const k = key?.trim() || null;
  memory = k;
  try {
    if (k) window.localStorage.setItem(STORAGE, k);
    else window.localStorage.removeItem(STORAGE);
  } catch {
    /* memory keeps it for this page */
  }
}

/** `headers` with the key's Authorization header added (when there is a key). */
export function withKeyHeader(headers?: HeadersInit): Headers {
  const out = new Headers(headers);
  const key = apiKey();
  if (key && !out.has('Authorization')) out.set('Authorization', `Bearer ${key}`);
  return out;
}

/** A websocket or event-stream URL with the key as its `api_key` query parameter (when there is a key). */
export function withKeyQuery(url: string): string {
  const key = apiKey();
  if (!key) return url;
  return `${url}${url.includes('?') ? '&' : '?'}api_key=${encodeURIComponent(key)}`;
}
