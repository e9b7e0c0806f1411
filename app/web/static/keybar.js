// The API-key bar in the page header: enter the key once (sessionStorage), forget it, and be asked
// for it when the service answers 401.

import { getKey, setKey } from './api.js';

/** Wire the #key-form in the header; `onChange` runs after the key was set or forgotten. */
export function initKeyBar(onChange) {
  const form = document.getElementById('key-form');
  const input = document.getElementById('api-key');
  const state = document.getElementById('key-state');
  const forget = document.getElementById('key-forget');
  const render = (note) => {
    const has = Boolean(getKey());
    state.textContent = note || (has ? 'API key set for this tab' : 'no API key');
    state.classList.toggle('warn', Boolean(note));
    forget.hidden = !has;
  };
  form.addEventListener('submit', (ev) => {
    ev.preventDefault();
    setKey(input.value.trim());
    input.value = '';
    render();
    onChange();
  });
  forget.addEventListener('click', () => { setKey(''); render(); onChange(); });
  document.addEventListener('ribpull:unauthorized', (ev) => {
    render(`this service needs an API key: ${ev.detail.detail || 'unauthorized'}`);
    if (document.activeElement !== input) input.focus();
  });
  render();
}
