// pbrl labelling page, 1 of 3: constants, state, the teacher's API, the pairs held
// (fetched, prefetched, answered, undone) and the shared clock. label-draw.js draws them;
// label-start.js wires the controls and keys, runs watch mode and starts the page. The
// three are classic scripts loaded in this order, sharing one global scope.
'use strict';

// ---------- constants and state ----------
const FPS = 10;                 // frames per second at 1x: the world's control rate, so 1x is real time
const CONTACT_N = 0.5;          // a force on the person above this is drawn as contact
const END_HOLD_S = 0.6;         // a looping clip rests on its last frame this long
const NAME_RE = /^[A-Za-z0-9 _.\-]{1,40}$/;
const NAME_KEY = 'pbrl.labeller';
const params = new URLSearchParams(location.search);
const TOKEN = params.get('token') || '';
const SIDES = ['left', 'right'];
const RANK_SIDES = ['r0', 'r1', 'r2', 'r3'];   // a ranking's attempts, in the order shown
const ORDINALS = ['1st', '2nd', '3rd', '4th'];
// The sides of a prepared query (a pair's left and right, or a ranking's attempts).
const sidesOf = (p) => (p && p.sides) || SIDES;
const COLORS = {
  furnitureFill: '#e5e7eb', furnitureLine: '#9ca3af',
  personFill: '#f5dcc8', personLine: '#c08a63',
  arm: '#374151', joint: '#ffffff',
  spoon: '#0284c7', trailDone: 'rgba(2,132,199,0.75)',
  food: '#d97706', foodLine: '#7c2d12', mouth: '#dc2626',
  path: 'rgba(2,132,199,0.22)', closest: '#111827', contact: '#dc2626', spill: '#ea580c',
  eaten: '#16a34a', leadIn: 'rgba(107,114,128,0.16)',
};
// The strips under each attempt: what a person would feel or see, from the teacher's replay.
const STRIPS = [
  { q: 'distance', name: 'distance to the mouth', unit: 'cm', scale: 100,
    nums: [['closest', 'closest'], ['mean', 'mean']], color: '#111827' },
  { q: 'speed', name: 'spoon speed', unit: 'cm/s', scale: 100,
    nums: [['mean', 'mean'], ['top', 'top']], color: '#0284c7' },
  { q: 'force', name: 'force on the person', unit: 'N', scale: 1,
    nums: [['peak', 'peak'], ['mean', 'mean']], color: '#dc2626' },
  { q: 'food', name: 'food', unit: '',
    nums: [['eaten', 'eaten'], ['spilled', 'spilled'], ['hits', 'on the person'], ['left', 'left on the spoon']] },
];
const FOOD_COLORS = ['#0284c7', '#16a34a', '#ea580c'];   // on the spoon, eaten, spilled (stacked)

const $ = (id) => document.getElementById(id);
// Watch mode: episodes embedded by `pbrl watch`, played without a teacher.
const WATCH = (() => {
  const el = document.getElementById('pbrl-watch');
  if (!el) return null;
  try { return JSON.parse(el.textContent); } catch (e) { return { error: String(e), pairs: [] }; }
})();
const S = {
  labeller: null,
  gen: 0,             // bumped when the pairs held are dropped (undo, new name): stale replies are ignored
  cur: null,          // the pair on screen (prepared, see prepare())
  pre: null,          // the prefetched next pair
  preGen: null,       // gen of the prefetch in flight, if any
  preTimer: null,
  nextGen: null,      // gen of the /next (no pair on screen) in flight, if any
  nextTimer: null,
  busy: false,        // an answer or undo POST in flight
  sitting: 0,         // answers given since the page was opened
  took: [],           // this sitting's times per answer, ms (its pace)
  total: null,        // answers by this labeller since the teacher started (server's count)
  unreachable: false,
  naming: false,      // the name dialog is open
  playing: false,
  t: 0,               // the shared clock, in frames
  hold: 0,            // seconds left resting on the last frame before looping
  speed: 1,
  loop: true,
  lastTs: null,
  drawn: -1,          // frame index last drawn
  dirty: true,
  answerAt: null,     // performance.now() of the last answer key press, until the next pair is drawn
  firstDone: false,
  msgTimer: null,
  waitText: 'Loading…',
  blank: false,       // the canvases are cleared (no pair)
  viewSig: '',
  canvases: { left: [], right: [] },   // per side: [{name, canvas, ctx, w, h}] (r0.. for a ranking)
  strips: { left: [], right: [] },     // per side: [{q, canvas, ctx, wrap, w, h}]
};
window.pbrlLastAnswerMs = null;
window.pbrlFirstPairMs = null;

// ---------- small helpers ----------
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const enc = encodeURIComponent;
const clamp = (x, a, b) => Math.max(a, Math.min(b, x));
const fin = (x) => typeof x === 'number' && Number.isFinite(x);

function loadName() {
  try { return localStorage.getItem(NAME_KEY); } catch (e) { return null; }
}
function saveName(n) {
  try { localStorage.setItem(NAME_KEY, n); } catch (e) { /* private mode: keep it for this page only */ }
}

function updateState() {
  let st;
  if (S.naming) st = 'name';
  else if (!S.cur) st = 'waiting';
  else st = S.playing ? 'playing' : 'paused';
  document.body.dataset.state = st;
  document.body.dataset.query = S.cur ? String(S.cur.query) : '';
  document.body.dataset.busy = S.busy ? '1' : '';
  const canAnswer = !!S.cur && !S.cur.answered && !S.busy && !S.naming;
  const ranking = !!S.cur && S.cur.kind === 'rank';
  document.body.dataset.kind = ranking ? 'rank' : 'pair';
  for (const id of ['btn-left', 'btn-right', 'btn-equal']) $(id).disabled = !canAnswer || ranking;
  $('btn-skip').disabled = !canAnswer;
  $('btn-send').disabled = !canAnswer || !ranking || !rankingDone(S.cur);
  $('btn-back').disabled = !canAnswer || !ranking || S.cur.picks.length === 0;
  renderPlaces();
  $('btn-undo').disabled = S.busy || !S.labeller || S.naming;
  $('play').disabled = !S.cur;
  $('scrub').disabled = !S.cur;
  $('play').textContent = S.playing ? 'Pause (Space)' : 'Play (Space)';
  if (!S.cur && !S.blank) blank();
  const ov = $('overlay');
  if (!S.cur && !S.naming) { $('overlay-text').textContent = S.waitText; ov.hidden = false; } else ov.hidden = true;
  // NOTE: the pair's display number, not the query id: a repeat shows under a new one.
  $('qid').textContent = S.cur ? (WATCH ? String(S.cur.display) : 'pair ' + S.cur.display) : '';
}

function showMsg(text, kind, ms) {
  const m = $('msg');
  m.textContent = text;
  m.className = kind || 'err';
  m.title = text;
  clearTimeout(S.msgTimer);
  if (ms) S.msgTimer = setTimeout(() => { m.textContent = ''; m.title = ''; }, ms);
}

function setUnreachable(u) {
  if (S.unreachable === u) return;
  S.unreachable = u;
  $('conn').hidden = !u;
}

// ---------- the API ----------
class NetError extends Error {}

// Returns {status, ok, data, error}; throws NetError when no HTTP response came.
async function api(method, path, body) {
  const headers = { 'Accept': 'application/json' };
  if (TOKEN) headers['Authorization'] = 'Bearer ' + TOKEN;
  const init = { method, headers, cache: 'no-store' };
  if (body !== undefined) { headers['Content-Type'] = 'application/json'; init.body = JSON.stringify(body); }
  const ctrl = new AbortController();
  const timer = setTimeout(() => ctrl.abort(), 20000);
  init.signal = ctrl.signal;
  let res, text;
  try {
    res = await fetch(path, init);
    text = res.status === 204 ? '' : await res.text();
  } catch (e) {
    setUnreachable(true);
    throw new NetError(String(e));
  } finally {
    clearTimeout(timer);
  }
  setUnreachable(false);
  let data = null;
  if (text) { try { data = JSON.parse(text); } catch (e) { data = null; } }
  if (res.status === 204) return { status: 204, ok: true, data: null };
  if (!res.ok) {
    let error = data && typeof data.error === 'string' ? data.error : 'HTTP ' + res.status;
    if (!data && text) error += ': ' + text.slice(0, 160);
    return { status: res.status, ok: false, data, error };
  }
  if (data === null || typeof data !== 'object') {
    return { status: res.status, ok: false, data: null, error: 'the teacher sent something that is not JSON' };
  }
  return { status: res.status, ok: true, data };
}

// ---------- status ----------
async function pollStatus() {
  let delay = 2000;
  if (S.labeller) {
    try {
      const r = await api('GET', 'api/v1/status?labeller=' + enc(S.labeller));
      if (r.ok) renderStatus(r.data); else showMsg('status: ' + r.error, 'err', 6000);
    } catch (e) {
      delay = 1000;
    }
  }
  setTimeout(pollStatus, delay);
}

function renderStatus(d) {
  const bits = [];
  if (d.run) bits.push('run ' + d.run);
  if (d.teacher) bits.push('teacher ' + d.teacher);
  if (fin(d.env_steps)) bits.push(d.env_steps.toLocaleString('en-US') + ' env steps');
  $('runinfo').textContent = bits.join(' · ');
  if (d.protocol !== undefined && d.protocol !== 1) {
    showMsg('the teacher speaks protocol ' + d.protocol + '; this page speaks 1', 'err');
  }
  $('p-open').textContent = fin(d.open) ? String(d.open) : '–';
  $('p-budget').textContent = fin(d.budget_left) ? String(d.budget_left) : '–';
  if (fin(d.answered)) { S.total = d.answered; renderCounts(); }
  const tr = $('p-training');
  // NOTE: a learner that keeps time with the person stops until their answers are in.
  const held = d.training && d.held === true;
  tr.className = 'chip ' + (held ? 'wait' : d.training ? 'training' : 'idle');
  $('p-training-text').textContent = held ? 'the robot has stopped: it waits for your answers'
    : d.training ? 'training' : 'learner not running';
  $('p-waiting').hidden = !d.waiting || held;
  // Where the person stands: how well the robot already predicts them, and the time the
  // rest of the sitting needs at their pace.
  const agreeing = fin(d.agreement) && fin(d.agreement_of) && d.agreement_of > 0;
  $('p-agree').hidden = !agreeing;
  if (agreeing) {
    const k = Math.round(d.agreement * d.agreement_of);
    $('p-agree-n').textContent = k + ' of your last ' + d.agreement_of +
      (d.agreement >= 0.9 && d.agreement_of >= 10 ? ' (more answers like these add little)' : '');
  }
  // NOTE: what is still to answer: the open queries and those the budget will still ask.
  const pace = median(S.took);
  const todo = fin(d.budget_left) ? d.budget_left + (fin(d.open) ? d.open : 0) : null;
  const left = todo !== null && pace !== null ? todo * pace / 1000 : null;
  $('p-left').hidden = left === null;
  if (left !== null) {
    $('p-left-t').textContent = left < 90 ? Math.max(1, Math.round(left)) + ' s' : Math.round(left / 60) + ' min';
  }
}

// The median of `xs`, or null for none.
function median(xs) {
  if (!xs.length) return null;
  const v = xs.slice().sort((a, b) => a - b);
  const m = v.length >> 1;
  return v.length % 2 ? v[m] : (v[m - 1] + v[m]) / 2;
}

function renderCounts() {
  $('p-sitting').textContent = String(S.sitting);
  // NOTE: the server's count lags an answer in flight; it is never below this sitting's.
  $('p-total').textContent = S.total !== null ? ' (' + Math.max(S.total, S.sitting) + ' in all)' : '';
}

// ---------- pairs ----------
// Checks a pair and works out what drawing it needs: frame counts and each view's bounds
// over both attempts (so A and B share one scale).
function prepare(p) {
  if (!p || typeof p !== 'object') throw new Error('not an object');
  if (p.query === undefined || p.query === null) throw new Error('no query id');
  const rank = p.kind === 'rank';
  if (rank && (!Array.isArray(p.attempts) || p.attempts.length < 3 || p.attempts.length > RANK_SIDES.length)) {
    throw new Error('a ranking needs 3 or 4 attempts');
  }
  const sides = rank ? RANK_SIDES.slice(0, p.attempts.length) : SIDES;
  const att = {};
  sides.forEach((side, i) => { att[side] = rank ? p.attempts[i] : p[side]; });
  const lastOf = [];
  for (const side of sides) {
    const a = att[side];
    if (!a || !a.frames || !Array.isArray(a.frames.spoon)) throw new Error('attempt ' + side + ' has no frames');
    const f = a.frames;
    const n = f.spoon.length;
    if (n < 1) throw new Error('attempt ' + side + ' has no frames');
    for (const k of ['arm', 'head', 'mouth', 'food']) {
      if (f[k] !== undefined && !Array.isArray(f[k])) throw new Error('attempt ' + side + ': frames.' + k + ' is not a list');
    }
    if (!Array.isArray(a.views) || a.views.length === 0) throw new Error('attempt ' + side + ' has no views');
    lastOf.push(n - 1);
  }
  const views = att[sides[0]].views.filter((v) => v && typeof v.name === 'string' && Array.isArray(v.axes) && v.axes.length === 2);
  if (views.length === 0) throw new Error('no usable views');
  const bounds = {};
  for (const v of views) {
    const [ia, ib] = v.axes;
    const b = { u0: Infinity, u1: -Infinity, v0: Infinity, v1: -Infinity };
    const add = (u, w, r) => {
      if (!fin(u) || !fin(w)) return;
      r = r || 0;
      if (u - r < b.u0) b.u0 = u - r;
      if (u + r > b.u1) b.u1 = u + r;
      if (w - r < b.v0) b.v0 = w - r;
      if (w + r > b.v1) b.v1 = w + r;
    };
    const addP = (q, r) => { if (Array.isArray(q)) add(q[ia], q[ib], r); };
    for (const side of sides) {
      // Drawn large around what matters: the spoon's whole path, the head and mouth and
      // the arm's last links. Furniture and the arm's base are drawn but may run off the
      // canvas; food is left out: the world has no floor, so a spilled particle keeps
      // falling and would shrink the scene to a dot.
      const a = att[side];
      const f = a.frames;
      const hr = fin(a.head_radius) ? a.head_radius : 0;
      for (const q of f.spoon) addP(q);
      for (const q of (f.head || [])) addP(q, hr);
      for (const q of (f.mouth || [])) addP(q);
      for (const fr of (f.arm || [])) if (Array.isArray(fr)) for (const q of fr.slice(-3)) addP(q);
    }
    if (!(b.u1 >= b.u0)) { b.u0 = -1; b.u1 = 1; b.v0 = -1; b.v1 = 1; }
    // at least 30 cm across, so an attempt that barely moves is not blown up
    for (const [lo, hi] of [['u0', 'u1'], ['v0', 'v1']]) {
      const grow = Math.max(0, 0.3 - (b[hi] - b[lo])) / 2;
      b[lo] -= grow; b[hi] += grow;
    }
    const mu = Math.max(0.03, (b.u1 - b.u0) * 0.06), mv = Math.max(0.03, (b.v1 - b.v0) * 0.06);
    b.u0 -= mu; b.u1 += mu; b.v0 -= mv; b.v1 += mv;
    bounds[v.name] = b;
  }
  const read = {};
  for (const side of sides) read[side] = readSide(att[side], side);
  // one scale per strip for every attempt, so they compare by eye
  const top = {};
  for (const st of STRIPS) {
    if (st.q === 'food') continue;
    let m = st.q === 'force' ? 1 : 1e-6;
    for (const side of sides) if (read[side]) for (const x of read[side].series[st.q]) if (x > m) m = x;
    top[st.q] = m;
  }
  return {
    query: p.query, display: p.display, raw: p, att, views, bounds, lastOf, read, top,
    kind: rank ? 'rank' : 'pair', sides,
    last: Math.max(...lastOf),
    replays: sides.map(() => 0), answered: false, shownAt: 0,
    picks: [], tieNext: false,   // a ranking's places so far: [{i, place}], best first
  };
}

// What a side's readout says over its judged frames (the lead-in is shown, not judged):
// the strips' series in display units, the numbers printed beside them, and the frames
// where contact and spills happen. Null when the teacher sent no readout.
function readSide(a, side) {
  const r = a.readout;
  const n = a.frames.spoon.length;
  if (!r || !Array.isArray(r.distance) || r.distance.length === 0) return null;
  for (const k of ['distance', 'speed', 'force', 'food']) {
    if (!Array.isArray(r[k]) || r[k].length !== n) {
      throw new Error('attempt ' + side + ': readout.' + k + ' has not one row per frame');
    }
  }
  const from = fin(a.segment_from) ? clamp(a.segment_from, 0, n - 1) : 0;
  // NOTE: frame k is the state after step k, so a segment's steps end at frames from+1..
  const j0 = Math.min(from + 1, n - 1);
  const num = (x) => (fin(x) ? x : 0);
  const series = {
    distance: r.distance.map((x) => num(x) * 100),
    speed: r.speed.map((x) => num(x) * 100),
    force: r.force.map(num),
  };
  const judged = (xs) => xs.slice(j0);
  const mean = (xs) => xs.reduce((t, x) => t + x, 0) / Math.max(1, xs.length);
  const dj = judged(series.distance);
  let closestAt = j0;
  for (let k = j0; k < n; k++) if (series.distance[k] < series.distance[closestAt]) closestAt = k;
  const food = r.food.map((c) => (Array.isArray(c) ? c.map((x) => num(x)) : [0, 0, 0, 0]));
  const at = (k, i) => food[k][i] || 0;
  const contact = [], spill = [], eaten = [];
  for (let k = 1; k < n; k++) {
    if (series.force[k] > CONTACT_N) contact.push(k);
    if (at(k, 2) > at(k - 1, 2)) spill.push(k);
    if (at(k, 1) > at(k - 1, 1)) eaten.push(k);
  }
  return {
    from, j0, series, food, closestAt, contact, spill, eaten,
    total: Math.max(1, ...food.map((c) => c[0] + c[1] + c[2])),
    nums: {
      distance: { closest: series.distance[closestAt].toFixed(1), mean: mean(dj).toFixed(1) },
      speed: { mean: mean(judged(series.speed)).toFixed(1), top: Math.max(0, ...judged(series.speed)).toFixed(1) },
      force: { peak: Math.max(0, ...judged(series.force)).toFixed(2), mean: mean(judged(series.force)).toFixed(2) },
      food: {
        eaten: String(at(n - 1, 1) - at(from, 1)),
        spilled: String(at(n - 1, 2) - at(from, 2)),
        hits: String(at(n - 1, 3) - at(from, 3)),
        left: String(at(n - 1, 0)),
      },
    },
  };
}

function dropHeld() {
  S.gen += 1;
  S.cur = null;
  S.pre = null;
  clearTimeout(S.preTimer);
  clearTimeout(S.nextTimer);
  S.answerAt = null;
  S.playing = false;
}

// Fetch a pair when none is on screen; polls every second while nothing is open.
async function loadNext() {
  if (!S.labeller || S.naming || S.cur || S.busy || S.nextGen === S.gen) return;
  clearTimeout(S.nextTimer);
  const gen = S.gen;
  S.nextGen = gen;
  let delay = 1000;
  try {
    const r = await api('GET', 'api/v1/next?labeller=' + enc(S.labeller));
    if (gen !== S.gen || S.cur) return;
    if (r.status === 204) {
      S.waitText = 'No pairs to label right now; waiting for the learner';
    } else if (r.ok) {
      let p = null;
      try { p = prepare(r.data); } catch (e) { showMsg('the teacher sent a pair this page cannot read: ' + e.message, 'err'); delay = 3000; }
      if (p) { showPair(p); prefetch(); return; }
    } else {
      showMsg(r.error, 'err', 8000);
      delay = 2000;
    }
  } catch (e) {
    // unreachable: the banner says so; try again in a second
  } finally {
    if (S.nextGen === gen) S.nextGen = null;
  }
  if (gen === S.gen && !S.cur) {
    updateState();
    S.nextTimer = setTimeout(loadNext, delay);
  }
}

// Fetch the pair after the one on screen, so an answer can show it at once.
function prefetch() {
  if (!S.labeller || !S.cur || S.pre || S.busy || S.preGen === S.gen) return;
  clearTimeout(S.preTimer);
  const gen = S.gen;
  const curQ = S.cur.query;
  S.preGen = gen;
  (async () => {
    let delay = 1000;
    try {
      const r = await api('GET', 'api/v1/next?labeller=' + enc(S.labeller) + '&exclude=' + enc(String(curQ)));
      if (gen !== S.gen) return;
      if (r.status === 204) {
        delay = 1000;
      } else if (r.ok) {
        try {
          const p = prepare(r.data);
          if (!S.cur) { showPair(p); delay = null; if (!S.busy) setTimeout(prefetch, 0); }
          else if (String(p.query) === String(S.cur.query)) delay = 1000;
          else { S.pre = p; delay = null; }
        } catch (e) {
          showMsg('the teacher sent a pair this page cannot read: ' + e.message, 'err');
          delay = 3000;
        }
      } else {
        showMsg(r.error, 'err', 8000);
        delay = 3000;
      }
    } catch (e) {
      delay = 1000;
    } finally {
      if (S.preGen === gen) S.preGen = null;
    }
    if (delay !== null && gen === S.gen) {
      if (S.cur && !S.pre) S.preTimer = setTimeout(prefetch, delay);
      else if (!S.cur && !S.busy) loadNext();
    }
  })();
}

function showPair(p) {
  S.cur = p;
  p.replays = p.sides.map(() => 0);
  p.answered = false;
  p.picks = [];
  p.tieNext = false;
  for (const side of SIDES.concat(RANK_SIDES)) $('att-' + side).hidden = !p.sides.includes(side);
  $('stage').style.setProperty('--n', String(p.sides.length));
  buildViews(p);
  showNumbers(p);
  S.t = 0; S.hold = 0; S.lastTs = null;
  const sc = $('scrub');
  sc.max = String(p.last);
  sc.value = '0';
  S.playing = true;
  draw();
  const now = performance.now();
  p.shownAt = now;
  if (!S.firstDone) { S.firstDone = true; window.pbrlFirstPairMs = now; }
  if (S.answerAt !== null) { window.pbrlLastAnswerMs = now - S.answerAt; S.answerAt = null; }
  // The counts change with each pair: refresh them now rather than at the next poll.
  if (!WATCH) api('GET', 'api/v1/status?labeller=' + enc(S.labeller))
    .then((r) => { if (r.ok) renderStatus(r.data); })
    .catch(() => {});
  updateState();
}

// ---------- rankings ----------
// A ranking is placed with keys: the attempts' numbers from best to worst (= ties the next
// one with the one before, Backspace takes the last back); the last attempt is placed by
// itself, and Enter sends.
function rankingDone(p) { return !!p && p.kind === 'rank' && p.picks.length === p.sides.length; }

function pick(i) {
  const p = S.cur;
  if (!p || p.kind !== 'rank' || p.answered || S.busy || i >= p.sides.length) return;
  if (p.picks.some((x) => x.i === i)) return;
  const last = p.picks[p.picks.length - 1];
  const place = p.tieNext && last ? last.place : p.picks.length;
  p.picks.push({ i, place });
  p.tieNext = false;
  if (p.picks.length === p.sides.length - 1) {
    const rest = p.sides.findIndex((_, k) => !p.picks.some((x) => x.i === k));
    p.picks.push({ i: rest, place: p.picks.length });
  }
  updateState();
}

function tieNext() {
  const p = S.cur;
  if (!p || p.kind !== 'rank' || p.picks.length === 0 || rankingDone(p)) return;
  p.tieNext = true;
  updateState();
}

function takeBack() {
  const p = S.cur;
  if (!p || p.kind !== 'rank' || p.answered || S.busy) return;
  // NOTE: the last attempt was placed by itself: taking back goes past it too.
  if (rankingDone(p)) p.picks.pop();
  p.picks.pop();
  p.tieNext = false;
  updateState();
}

function renderPlaces() {
  const p = S.cur;
  const ranking = !!p && p.kind === 'rank';
  RANK_SIDES.forEach((side, i) => {
    const el = $('place-' + side);
    const x = ranking ? p.picks.find((y) => y.i === i) : null;
    el.textContent = x ? (p.picks.filter((y) => y.place === x.place).length > 1 ? 'tied ' : '') + ORDINALS[x.place] : '';
    el.hidden = !x;
  });
  if (!ranking) return;
  $('rank-hint').textContent = rankingDone(p)
    ? 'Ranked: Enter sends it (Backspace takes the last back)'
    : (p.tieNext ? 'The next one ties with the one before: press its number'
      : 'Press the attempts\u2019 numbers from best to worst (= ties the next with the one before)');
}

async function sendRanking() {
  const p = S.cur;
  if (!rankingDone(p)) return;
  const places = p.sides.map((_, i) => p.picks.find((x) => x.i === i).place);
  await send({ places });
}

// ---------- answers ----------
async function answer(choice) {
  if (choice !== 'skip' && S.cur && S.cur.kind === 'rank') return;
  await send({ choice });
}

// Send an answer (a pair's choice, or a ranking's places) to the pair on screen.
async function send(verdict) {
  const t0 = performance.now();
  const cur = S.cur;
  if (!cur || cur.answered || S.busy || S.naming || !S.labeller) return;
  cur.answered = true;
  S.busy = true;
  const body = Object.assign({
    labeller: S.labeller, query: cur.query,
    took_ms: Math.max(0, Math.round(t0 - cur.shownAt)),
    replays: cur.kind === 'rank' ? [0, 0] : cur.replays.slice(),
  }, verdict);
  if (verdict.choice !== 'skip') S.took.push(body.took_ms);
  // Show the prefetched pair at once; the answer buttons stay off until the POST is through.
  S.answerAt = t0;
  if (S.pre) {
    const p = S.pre;
    S.pre = null;
    showPair(p);
  } else {
    // a prefetch still in flight shows its pair when it lands (see prefetch())
    clearTimeout(S.preTimer);
    S.cur = null;
    S.playing = false;
    S.waitText = 'Loading…';
  }
  updateState();
  // Retried until an HTTP response comes. A 409 ("already answered") means an earlier try
  // got there (the browser itself may resend a POST whose connection dropped): done.
  for (;;) {
    try {
      const r = await api('POST', 'api/v1/answer', body);
      if (r.ok) {
        S.sitting += 1;
        if (fin(r.data.answered)) S.total = r.data.answered;
      } else if (r.status === 409 && !(r.data && r.data.by_you === false)) {
        S.sitting += 1;
        if (S.total !== null) S.total += 1;
      } else {
        showMsg('your answer to the previous pair was not recorded: ' + r.error, 'err', 8000);
      }
      break;
    } catch (e) {
      await sleep(1000);
    }
  }
  renderCounts();
  S.busy = false;
  updateState();
  // Only now may /next be asked again: before, the answered query was still open.
  if (S.cur) prefetch();
  else if (S.preGen !== S.gen) loadNext();
}

async function undo() {
  if (!S.labeller || S.busy || S.naming) return;
  S.busy = true;
  updateState();
  try {
    const r = await api('POST', 'api/v1/undo', { labeller: S.labeller });
    if (r.ok) {
      S.sitting = Math.max(0, S.sitting - 1);
      if (S.total !== null) S.total = Math.max(0, S.total - 1);
      renderCounts();
      showMsg('Undone: that pair comes back now', 'info', 3000);
      // The withdrawn query comes back from the next /next: drop what we hold and ask again.
      dropHeld();
      S.waitText = 'Loading…';
      S.busy = false;
      updateState();
      loadNext();
      return;
    }
    showMsg(r.error, 'err', 3000);
  } catch (e) {
    showMsg('teacher unreachable: undo not sent', 'err', 3000);
  }
  S.busy = false;
  updateState();
  if (S.cur) prefetch(); else loadNext();
}

// ---------- playback ----------
function setPlaying(on) {
  if (!S.cur) return;
  if (on && S.t >= S.cur.last && S.hold <= 0) S.t = 0;   // play again from the start
  S.playing = on;
  S.lastTs = null;
  updateState();
}

function advance(dt) {
  const p = S.cur;
  if (S.hold > 0) {
    S.hold -= dt;
    if (S.hold <= 0) { S.hold = 0; S.t = 0; if (WATCH) watchStep(1); }
    return;
  }
  const prev = S.t;
  const next = prev + dt * FPS * S.speed;
  // A side counts as played through when the shared clock passes its last frame.
  for (let i = 0; i < p.lastOf.length; i++) if (prev < p.lastOf[i] && next >= p.lastOf[i]) p.replays[i] += 1;
  if (next >= p.last) {
    S.t = p.last;
    if (S.loop) S.hold = END_HOLD_S;
    else { S.playing = false; updateState(); }
  } else {
    S.t = next;
  }
}

function tick(ts) {
  requestAnimationFrame(tick);
  if (!S.cur) return;
  if (S.playing && !S.naming) {
    if (S.lastTs === null) S.lastTs = ts;
    const dt = Math.min(0.25, Math.max(0, (ts - S.lastTs) / 1000));
    S.lastTs = ts;
    advance(dt);
  } else {
    S.lastTs = null;
  }
  // NOTE: drawn at every animation frame while playing: positions are interpolated
  // between the world's frames (10 a second), so motion is smooth.
  if (S.playing || Math.floor(S.t) !== S.drawn || S.dirty) draw();
}
