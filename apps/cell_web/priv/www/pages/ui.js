// Small helpers shared by the panel's pages (pages/*.js): building elements and SVG,
// times and durations in words an operator reads. A classic script, loaded before
// the pages; it defines window.cellUi.
'use strict';

window.cellUi = (() => {
  const SVG = 'http://www.w3.org/2000/svg';

  // el('button', {class: 'small', testid: 'save', on: {click: fn}}, 'Save')
  function build(node, attrs, children) {
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === undefined || v === null || v === false) continue;
      if (k === 'class') node.setAttribute('class', v);
      else if (k === 'text') node.textContent = v;
      else if (k === 'testid') node.dataset.testid = v;
      else if (k === 'data') Object.assign(node.dataset, v);
      else if (k === 'on') for (const [ev, fn] of Object.entries(v)) node.addEventListener(ev, fn);
      else if (k in node && !(node instanceof SVGElement)) node[k] = v;
      else node.setAttribute(k, v === true ? '' : String(v));
    }
    for (const c of children.flat(Infinity)) {
      if (c === null || c === undefined || c === false) continue;
      node.append(c instanceof Node ? c : document.createTextNode(String(c)));
    }
    return node;
  }
  const el = (tag, attrs, ...children) => build(document.createElement(tag), attrs, children);
  const svg = (tag, attrs, ...children) => build(document.createElementNS(SVG, tag), attrs, children);

  const pad = (n, w = 2) => String(n).padStart(w, '0');
  // A time as local date and clock: 2026-11-27 14:05:09.
  function time(ms) {
    if (ms === null || ms === undefined) return '—';
    const d = new Date(ms);
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
      `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }
  const clock = (ms) => { const d = new Date(ms); return `${pad(d.getHours())}:${pad(d.getMinutes())}`; };
  // A duration in the largest units that read well: 850 ms, 12.5 s, 3 min 20 s, 2 h 05 min.
  function duration(ms) {
    if (ms === null || ms === undefined) return '—';
    if (ms < 1000) return `${Math.round(ms)} ms`;
    if (ms < 60000) return `${(ms / 1000).toFixed(1)} s`;
    const s = Math.round(ms / 1000);
    if (s < 3600) return `${Math.floor(s / 60)} min ${pad(s % 60)} s`;
    return `${Math.floor(s / 3600)} h ${pad(Math.floor((s % 3600) / 60))} min`;
  }
  const percent = (x) => (x === null || x === undefined ? '—' : `${(x * 100).toFixed(1)} %`);
  // A value for datetime-local inputs, and back.
  const localInput = (ms) => time(ms).replace(' ', 'T').slice(0, 16);
  const fromInput = (text) => (text ? new Date(text).getTime() : undefined);

  // Runs an API call; a refusal is shown as a toast and returns undefined.
  async function attempt(panel, fn) {
    try { return await fn(); } catch (e) { panel.toast(e.message); return undefined; }
  }

  // Sends a file as the body of a request (the API's JSON helper sends JSON only);
  // answers the parsed JSON, or throws an Error with the cell's message.
  async function send(panel, method, path, file, type) {
    const headers = { accept: 'application/json', 'content-type': type };
    const { csrf } = panel.session();
    if (csrf) headers['x-csrf-token'] = csrf;
    const res = await fetch(path, { method, headers, credentials: 'same-origin', body: file });
    const data = await res.json().catch(() => ({ message: res.statusText }));
    if (!res.ok) {
      const err = new Error(data.message || res.statusText);
      err.status = res.status;
      err.code = data.error;
      throw err;
    }
    return data;
  }

  return { send, el, svg, time, clock, duration, percent, localInput, fromInput, attempt };
})();
