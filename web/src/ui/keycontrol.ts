// The header's API key button and its small form (api/key.ts keeps the key).
import { apiKey, setApiKey } from '../api/key';
import { h } from './dom';

/** The key button of the header: a small form to enter, replace or forget the person's API key (needed
 * when the services run with API_KEYS); `changed` runs after a change (the page is drawn again). */
export function keyControl(el: HTMLElement, changed: () => void): void {
  const button = h('button', { type: 'button', class: 'key-button', 'data-testid': 'key-button' }, '');
  const input = h('input', { type: 'password', placeholder: 'API key', autocomplete: 'off', 'data-testid': 'key-input' });
  const save = h('button', { type: 'submit', 'data-testid': 'key-save' }, 'Use key');
  const forget = h('button', { type: 'button', 'data-testid': 'key-forget' }, 'Forget');
  const form = h('form', { class: 'key-form', hidden: true }, input, save, forget);
  const label = (): void => {
    button.textContent = apiKey() ? 'API key: set' : 'API key';
    button.title = apiKey() ? 'The dashboard sends your API key with every call' : 'Enter an API key (when the services ask for one)';
  };
  button.addEventListener('click', () => {
    form.hidden = !form.hidden;
    if (!form.hidden) input.focus();
  });
  form.addEventListener('submit', (ev) => {
    ev.preventDefault();
    setApiKey(input.value);
    input.value = '';
    form.hidden = true;
    label();
    changed();
  });
  forget.addEventListener('click', () => {
    setApiKey(null);
    form.hidden = true;
    label();
    changed();
  });
  label();
  el.append(button, form);
}
