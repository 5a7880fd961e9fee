// pbrl labelling page, 3 of 3: the name dialog, controls and keys, watch mode (`pbrl
// watch`) and the start. Loaded last: its top-level code runs with label.js and
// label-draw.js in place.
'use strict';

// ---------- the name ----------
function openNameDialog(allowCancel, prefill, hint) {
  S.naming = true;
  $('name-dialog').hidden = false;
  $('name-cancel').hidden = !allowCancel;
  const inp = $('name-input');
  inp.value = prefill || '';
  const h = $('name-hint');
  h.textContent = hint || '1–40 characters: letters, digits, space, _ . -';
  h.className = hint ? 'hint err' : 'hint';
  updateState();
  setTimeout(() => inp.focus(), 0);
}

function closeNameDialog() {
  S.naming = false;
  $('name-dialog').hidden = true;
  $('name-input').blur();
  S.lastTs = null;
  updateState();
}

function setLabeller(name) {
  const changed = name !== S.labeller;
  S.labeller = name;
  $('who-name').textContent = name;
  $('who').hidden = false;
  if (changed) {
    dropHeld();
    S.sitting = 0;
    S.total = null;
    renderCounts();
    S.waitText = 'Loading…';
  }
  updateState();
  loadNext();
}

$('name-form').addEventListener('submit', (e) => {
  e.preventDefault();
  const name = $('name-input').value.trim();
  if (!NAME_RE.test(name)) {
    const h = $('name-hint');
    h.textContent = name ? 'Only letters, digits, space, _ . - (at most 40)' : 'Please type a name';
    h.className = 'hint err';
    return;
  }
  saveName(name);
  closeNameDialog();
  setLabeller(name);
});
$('name-cancel').addEventListener('click', () => { closeNameDialog(); });
$('name-dialog').addEventListener('keydown', (e) => {
  if (e.key === 'Escape' && !$('name-cancel').hidden) { e.preventDefault(); closeNameDialog(); }
});
$('change-name').addEventListener('click', (e) => {
  e.preventDefault();
  openNameDialog(!!S.labeller, S.labeller || '');
});

// ---------- controls and keys ----------
for (const id of ['btn-left', 'btn-right', 'btn-equal', 'btn-skip']) {
  $(id).addEventListener('click', (e) => { answer(e.currentTarget.dataset.choice); });
}
$('btn-undo').addEventListener('click', () => undo());
$('btn-send').addEventListener('click', () => sendRanking());
$('btn-back').addEventListener('click', () => takeBack());
// A ranking's attempt is placed by clicking it too (the next place, best first).
RANK_SIDES.forEach((side, i) => { $('att-' + side).addEventListener('click', () => pick(i)); });
$('play').addEventListener('click', () => setPlaying(!S.playing));
// clicking a button should not leave it focused (Space would press it again)
for (const el of document.querySelectorAll('button, select, input[type=checkbox]')) {
  if (el.closest('#name-dialog')) continue;
  el.addEventListener('mousedown', (e) => { if (el.tagName === 'BUTTON') e.preventDefault(); });
}
$('scrub').addEventListener('input', (e) => {
  if (!S.cur) return;
  if (S.playing) showMsg('Paused while you look frame by frame: Space or Play plays on', 'info', 4000);
  S.playing = false;
  S.hold = 0;
  S.t = clamp(Number(e.target.value) || 0, 0, S.cur.last);
  draw();
  updateState();
});
$('scrub').addEventListener('change', (e) => e.target.blur());
$('speed').addEventListener('change', (e) => { S.speed = Number(e.target.value) || 1; e.target.blur(); });
$('loop').addEventListener('change', (e) => { S.loop = e.target.checked; e.target.blur(); });

function isTextField(el) {
  if (!el || !el.tagName) return false;
  if (el.isContentEditable || el.tagName === 'TEXTAREA') return true;
  return el.tagName === 'INPUT' && !['checkbox', 'range', 'radio', 'button', 'submit'].includes(el.type);
}

window.addEventListener('keydown', (e) => {
  if (S.naming || isTextField(e.target)) return;
  const k = e.key;
  let act = null;
  if ((e.ctrlKey || e.metaKey) && !e.altKey && !e.shiftKey && (k === 'z' || k === 'Z')) {
    act = undo;
  } else if (!e.ctrlKey && !e.metaKey && !e.altKey && S.cur && S.cur.kind === 'rank' && !WATCH) {
    // A ranking: the attempts' numbers from best to worst.
    if (k >= '1' && k <= '4') act = () => pick(Number(k) - 1);
    else if (k === '=') act = tieNext;
    else if (k === 'Backspace') act = takeBack;
    else if (k === 'Enter') act = sendRanking;
    else if (k === 's' || k === 'S') act = () => answer('skip');
    else if (k === 'u' || k === 'U') act = undo;
    else if (k === ' ' || k === 'Spacebar') act = () => setPlaying(!S.playing);
  } else if (!e.ctrlKey && !e.metaKey && !e.altKey) {
    if (k === 'ArrowLeft') act = WATCH ? () => watchStep(-1) : () => answer('left');
    else if (k === 'ArrowRight') act = WATCH ? () => watchStep(1) : () => answer('right');
    else if (k === '=') act = () => answer('equal');
    else if (k === 's' || k === 'S') act = () => answer('skip');
    else if (k === 'u' || k === 'U') act = undo;
    else if (k === ' ' || k === 'Spacebar') act = () => setPlaying(!S.playing);
  }
  if (!act) return;
  e.preventDefault();
  e.stopPropagation();
  if (e.repeat) return;   // a held key answers once
  act();
}, true);
window.addEventListener('keyup', (e) => {
  if (!S.naming && !isTextField(e.target) && e.key === ' ') e.preventDefault();
}, true);

// ---------- watch mode ----------
function startWatch() {
  document.body.dataset.mode = 'watch';
  const title = WATCH.title || 'what the robot learnt';
  document.title = 'pbrl watch · ' + title;
  $('page-sub').textContent = '· ' + title;
  $('runinfo').textContent = WATCH.info || '';
  const names = Array.isArray(WATCH.names) ? WATCH.names : ['A', 'B'];
  SIDES.forEach((side, i) => {
    const h = $(side === 'left' ? 'att-left' : 'att-right').querySelector('h2');
    h.textContent = '';
    const tag = document.createElement('span');
    tag.className = 'tag';
    tag.textContent = i ? 'B' : 'A';
    h.appendChild(tag);
    h.appendChild(document.createTextNode(String(names[i] || '')));
  });
  S.watch = { pairs: [], at: 0 };
  try {
    for (const raw of WATCH.pairs || []) S.watch.pairs.push(prepare(raw));
  } catch (e) {
    showMsg('this file holds episodes the page cannot read: ' + e.message, 'err');
  }
  if (WATCH.error) showMsg('this file is damaged: ' + WATCH.error, 'err');
  if (!S.watch.pairs.length) { S.waitText = 'No episodes in this file'; updateState(); return; }
  if (WATCH.capture) { capture(WATCH.capture); return; }
  showPair(S.watch.pairs[0]);
  requestAnimationFrame(tick);
}

function watchStep(d) {
  const w = S.watch;
  if (!w || !w.pairs.length) return;
  w.at = (w.at + d + w.pairs.length) % w.pairs.length;
  const playing = S.playing;
  showPair(w.pairs[w.at]);
  S.playing = playing || d > 0;
  updateState();
}

// Every `step`-th frame of each pair drawn with the page's own drawing (drawAttempt,
// drawStrip) into one picture `width` wide: both attempts' views, their strips with the
// numbers, and the clock; left as PNG data URLs in <pre id="pbrl-frames">.
function capture(c) {
  const step = Math.max(1, Math.floor(c.step || 1));
  const W = Math.max(480, Math.floor(c.width || 960));
  const col = Math.floor(W / 2), pad = 8;
  const nv = S.watch.pairs[0].views.length;
  const vw = Math.floor((col - 2 * pad) / nv), vh = Math.floor(vw * 0.85);
  const stripH = 18, stripGap = 30, head = 30, foot = 24;
  const H = head + 16 + vh + 8 + STRIPS.length * stripGap + foot;
  const sub = (w, h) => {
    const canvas = document.createElement('canvas');
    canvas.width = w; canvas.height = h;
    return { canvas, ctx: canvas.getContext('2d'), w, h, dpr: 1 };
  };
  const views = SIDES.map(() => Array.from({ length: nv }, () => sub(vw, vh)));
  const strips = SIDES.map(() => STRIPS.map((st) => Object.assign(sub(col - 2 * pad, stripH), { q: st.q })));
  const out = sub(W, H);
  const ctx = out.ctx;
  const names = Array.isArray(WATCH.names) ? WATCH.names : ['A', 'B'];
  const frames = [];
  for (const p of S.watch.pairs) {
    for (let t = 0; t <= p.last; t += step) {
      ctx.setTransform(1, 0, 0, 1, 0, 0);
      ctx.fillStyle = '#ffffff';
      ctx.fillRect(0, 0, W, H);
      SIDES.forEach((side, i) => {
        const x0 = i * col, ts = Math.min(t, p.lastOf[i]);
        ctx.fillStyle = i ? '#7c3aed' : '#0f766e';
        ctx.font = '600 15px system-ui, sans-serif';
        ctx.textBaseline = 'middle';
        ctx.textAlign = 'left';
        ctx.fillText((i ? 'B  ' : 'A  ') + String(names[i] || ''), x0 + pad, head / 2 + 2);
        p.views.forEach((v, vi) => {
          const b = p.bounds[v.name];
          const s = Math.max(1e-6, Math.min((vw - 2 * pad) / (b.u1 - b.u0), (vh - 2 * pad) / (b.v1 - b.v0)));
          const cv = views[i][vi];
          drawAttempt(cv, v, p.att[side], p.read[side], ts, b, s);
          leadIn(cv, p.att[side], Math.floor(t));
          const vx = x0 + pad + vi * vw;
          ctx.fillStyle = '#6b7280';
          ctx.font = '12px system-ui, sans-serif';
          ctx.fillText(v.title || v.name, vx + 4, head + 8);
          ctx.strokeStyle = '#e5e7eb';
          ctx.strokeRect(vx + 0.5, head + 16.5, vw - 1, vh - 1);
          ctx.drawImage(cv.canvas, vx, head + 16);
        });
        const r = p.read[side];
        STRIPS.forEach((st, si) => {
          const y = head + 16 + vh + 8 + si * stripGap;
          let text = st.name;
          if (r) {
            text += ': ' + st.nums.map(([key, lab]) => lab + ' ' + r.nums[st.q][key]).join(' · ') + (st.unit ? ' ' + st.unit : '');
          }
          ctx.fillStyle = '#374151';
          ctx.font = '11px system-ui, sans-serif';
          ctx.fillText(text, x0 + pad, y + 5);
          const sc = strips[i][si];
          drawStrip(sc, p, side, ts);
          ctx.drawImage(sc.canvas, x0 + pad, y + 11);
        });
      });
      ctx.fillStyle = '#374151';
      ctx.font = '12px system-ui, sans-serif';
      ctx.textAlign = 'left';
      ctx.fillText(String(p.display) + ' · ' + (t / FPS).toFixed(1) + ' s of ' + (p.last / FPS).toFixed(1) + ' s', pad, H - foot / 2);
      frames.push(out.canvas.toDataURL('image/png'));
    }
  }
  const pre = document.createElement('pre');
  pre.id = 'pbrl-frames';
  pre.hidden = true;
  pre.textContent = JSON.stringify({ width: W, height: H, delay_ms: Math.round(1000 * step / FPS), frames });
  document.body.appendChild(pre);
  document.body.dataset.captured = String(frames.length);
}

// ---------- start ----------
// The labeller's name: from the address, else the one this browser kept, else asked for.
function startLabelling() {
  requestAnimationFrame(tick);
  pollStatus();
  const fromUrl = params.get('labeller');
  const stored = loadName();
  if (fromUrl !== null) {
    const n = fromUrl.trim();
    if (NAME_RE.test(n)) setLabeller(n);
    else openNameDialog(false, n, 'The name in the address is not usable: 1–40 letters, digits, space, _ . -');
  } else if (stored && NAME_RE.test(stored)) {
    setLabeller(stored);
  } else {
    openNameDialog(false, '');
  }
}

renderCounts();
updateState();
if (WATCH) startWatch();
else startLabelling();
