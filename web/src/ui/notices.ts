// Messages to the person: errors from the services in plain words, at the top of the page.
// A notice with an id replaces the previous one of that id and can be cleared by it.

export type NoticeKind = 'error' | 'warning' | 'info';

let host: HTMLElement | null = null;

export function initNotices(el: HTMLElement): void {
  host = el;
}

export function notify(message: string, kind: NoticeKind = 'error', id?: string): void {
  if (!host) return;
  if (id) clearNotice(id);
  const box = document.createElement('div');
  box.className = `notice notice-${kind}`;
  if (id) box.dataset.id = id;
  const text = document.createElement('span');
  text.textContent = message;
  const close = document.createElement('button');
  close.className = 'notice-close';
  close.textContent = '×';
  close.title = 'Dismiss';
  close.addEventListener('click', () => box.remove());
  box.append(text, close);
  host.append(box);
  while (host.children.length > 5) host.firstElementChild?.remove();
}

export function clearNotice(id: string): void {
  host?.querySelectorAll(`[data-id="${CSS.escape(id)}"]`).forEach((n) => n.remove());
}

export function clearAll(): void {
  if (host) host.textContent = '';
}
