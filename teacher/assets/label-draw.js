// pbrl labelling page, 2 of 3: the canvases and the strips under them, and drawing an
// attempt at a clock time (label.js holds the state it reads).
'use strict';

// ---------- drawing ----------
function buildViews(p) {
  const sides = sidesOf(p);
  const sig = sides.join(',') + ':' + p.views.map((v) => v.name + '|' + v.title).join('/');
  if (sig === S.viewSig) return;
  S.viewSig = sig;
  ro.disconnect();
  for (const side of Object.keys(S.canvases)) if (!sides.includes(side)) { S.canvases[side] = []; S.strips[side] = []; }
  for (const side of sides) {
    const host = $('att-' + side).querySelector('.views');
    host.textContent = '';
    S.canvases[side] = [];
    for (const v of p.views) {
      const box = document.createElement('div');
      box.className = 'view';
      const t = document.createElement('div');
      t.className = 'vtitle';
      t.textContent = v.title || v.name;
      const wrap = document.createElement('div');
      wrap.className = 'cwrap';
      const c = document.createElement('canvas');
      wrap.appendChild(c);
      box.appendChild(t);
      box.appendChild(wrap);
      host.appendChild(box);
      S.canvases[side].push({ name: v.name, canvas: c, ctx: c.getContext('2d'), wrap, w: 0, h: 0 });
    }
  }
  for (const side of sides) {
    const host = $('att-' + side);
    const old = host.querySelector('.strips');
    if (old) old.remove();
    const box = document.createElement('div');
    box.className = 'strips';
    const head = document.createElement('div');
    head.className = 'judged';
    head.appendChild(document.createTextNode('Numbers: the '));
    const js = document.createElement('b');
    js.dataset.v = 'judged-s';
    head.appendChild(js);
    head.appendChild(document.createTextNode(' s you judge · strips: the whole clip (grey: lead-in)'));
    box.appendChild(head);
    S.strips[side] = [];
    for (const st of STRIPS) {
      const row = document.createElement('div');
      row.className = 'strip';
      row.dataset.q = st.q;
      const sl = document.createElement('div');
      sl.className = 'sl';
      const name = document.createElement('span');
      name.className = 'name';
      name.textContent = st.name;
      const nums = document.createElement('span');
      nums.className = 'nums';
      st.nums.forEach(([key, label], i) => {
        if (i) nums.appendChild(document.createTextNode(' · '));
        if (st.q === 'food' && i < 3) {
          const sw = document.createElement('span');
          sw.className = 'sw';
          sw.style.background = [FOOD_COLORS[1], FOOD_COLORS[2], COLORS.contact][i];
          nums.appendChild(sw);
          nums.appendChild(document.createTextNode(' '));
        }
        nums.appendChild(document.createTextNode(label + ' '));
        const b = document.createElement('b');
        b.dataset.v = key;
        b.textContent = '–';
        nums.appendChild(b);
      });
      if (st.unit) nums.appendChild(document.createTextNode(' ' + st.unit));
      sl.appendChild(name);
      sl.appendChild(nums);
      const sbox = document.createElement('div');
      sbox.className = 'sbox';
      const c = document.createElement('canvas');
      sbox.appendChild(c);
      row.appendChild(sl);
      row.appendChild(sbox);
      box.appendChild(row);
      S.strips[side].push({ q: st.q, name: st.q, canvas: c, ctx: c.getContext('2d'), wrap: sbox, w: 0, h: 0 });
    }
    host.appendChild(box);
  }
  measure();
  for (const side of sides) for (const c of S.canvases[side].concat(S.strips[side])) ro.observe(c.wrap);
}

// The numbers beside the strips, for the pair now on screen.
function showNumbers(p) {
  for (const side of sidesOf(p)) {
    const host = $('att-' + side);
    const r = p.read[side];
    for (const el of host.querySelectorAll('.strip [data-v]')) {
      const q = el.closest('.strip').dataset.q;
      el.textContent = r ? r.nums[q][el.dataset.v] : '–';
    }
    const n = p.att[side].frames.spoon.length - 1;
    const from = r ? r.from : 0;
    host.querySelector('.strips [data-v=judged-s]').textContent = ((n - from) / FPS).toFixed(1);
  }
  const a = p.att[sidesOf(p)[0]];
  const n = a.frames.spoon.length - 1;
  const lead = fin(a.segment_from) ? a.segment_from : 0;
  $('clip-len').textContent = (n / FPS).toFixed(1) + ' s' +
    (lead > 0 ? ' (' + (lead / FPS).toFixed(1) + ' s of lead-in, then ' + ((n - lead) / FPS).toFixed(1) + ' s to judge)' : '');
}

function measure() {
  const dpr = window.devicePixelRatio || 1;
  for (const side of Object.keys(S.canvases)) {
    for (const c of S.canvases[side].concat(S.strips[side] || [])) {
      const r = c.wrap.getBoundingClientRect();
      const w = Math.max(1, Math.floor(r.width)), h = Math.max(1, Math.floor(r.height));
      if (w !== c.w || h !== c.h || c.dpr !== dpr) {
        c.w = w; c.h = h; c.dpr = dpr;
        c.canvas.width = Math.round(w * dpr);
        c.canvas.height = Math.round(h * dpr);
      }
    }
  }
  S.dirty = true;
}

const ro = new ResizeObserver(() => { measure(); if (S.cur) draw(); });

// No pair: nothing of the last one may linger on screen.
function blank() {
  S.blank = true;
  for (const side of Object.keys(S.canvases)) {
    for (const c of S.canvases[side].concat(S.strips[side] || [])) {
      c.ctx.setTransform(1, 0, 0, 1, 0, 0);
      c.ctx.clearRect(0, 0, c.canvas.width, c.canvas.height);
    }
  }
  for (const el of document.querySelectorAll('.strips [data-v]')) el.textContent = '–';
  $('scrub').value = '0';
  $('frameinfo').textContent = '–';
}

function draw() {
  const p = S.cur;
  S.dirty = false;
  if (!p) return;
  S.blank = false;
  const f = Math.floor(S.t);
  S.drawn = f;
  document.body.dataset.frame = String(f);
  const sides = sidesOf(p);
  for (let vi = 0; vi < p.views.length; vi++) {
    const v = p.views[vi];
    const cs = sides.map((side) => S.canvases[side][vi]);
    if (cs.some((c) => !c)) continue;
    // one scale for every attempt: fit the smallest of their canvases
    const b = p.bounds[v.name];
    const pad = 8;
    const w = Math.min(...cs.map((c) => c.w)) - 2 * pad, h = Math.min(...cs.map((c) => c.h)) - 2 * pad;
    const s = Math.max(1e-6, Math.min(w / (b.u1 - b.u0), h / (b.v1 - b.v0)));
    sides.forEach((side, i) => {
      drawAttempt(cs[i], v, p.att[side], p.read[side], Math.min(S.t, p.lastOf[i]), b, s);
      leadIn(cs[i], p.att[side], f);
    });
  }
  sides.forEach((side, i) => {
    for (const st of S.strips[side]) drawStrip(st, p, side, Math.min(S.t, p.lastOf[i]));
  });
  const sc = $('scrub');
  if (String(f) !== sc.value) sc.value = String(f);
  $('frameinfo').textContent = (S.t / FPS).toFixed(1) + ' s / ' + (p.last / FPS).toFixed(1) + ' s' +
    (S.playing ? '' : ' · paused');
}

// The frames before a segment are its lead-in: shown so a person sees where the judged
// part starts, and marked as not judged.
function leadIn(c, a, f) {
  if (!fin(a.segment_from) || f >= a.segment_from) return;
  const ctx = c.ctx;
  ctx.save();
  ctx.font = '600 13px system-ui, sans-serif';
  ctx.fillStyle = 'rgba(90, 90, 90, 0.9)';
  ctx.textAlign = 'left';
  ctx.textBaseline = 'top';
  ctx.fillText('lead-in, not judged', 8, 8);
  ctx.restore();
}

// A point of `list` at clock `t` (frames, fractional): between two frames, the straight
// line between them, unless the point jumped (eaten food leaves the world).
function lerpAt(list, t) {
  if (!Array.isArray(list) || !list.length) return null;
  const i = clamp(Math.floor(t), 0, list.length - 1);
  const a = list[i], b = list[Math.min(i + 1, list.length - 1)];
  const x = t - i;
  if (x <= 0 || a === b || !Array.isArray(a) || !Array.isArray(b) || a.length !== b.length) return a;
  let d2 = 0;
  for (let k = 0; k < a.length; k++) {
    if (!fin(a[k]) || !fin(b[k])) return a;
    d2 += (b[k] - a[k]) ** 2;
  }
  if (d2 > 0.25) return x < 0.5 ? a : b;
  return a.map((ak, k) => ak + (b[k] - ak) * x);
}

// The points of a per-frame list of point lists (the arm, the food) at clock `t`.
function between(frames, t) {
  if (!Array.isArray(frames) || !frames.length) return [];
  const i = clamp(Math.floor(t), 0, frames.length - 1);
  const a = frames[i], b = frames[Math.min(i + 1, frames.length - 1)];
  if (!Array.isArray(a)) return [];
  if (!Array.isArray(b) || b.length !== a.length) return a;
  return a.map((q, j) => lerpAt([q, b[j]], t - i));
}

// Where a view's world coordinates land on canvas `c`: the bounds `b` at scale `s`,
// centred, on the view's two axes. What every layer of an attempt draws with.
function viewport(c, v, b, s) {
  const [ia, ib] = v.axes;
  const ox = (c.w - (b.u1 - b.u0) * s) / 2 - b.u0 * s;
  const oy = (c.h + (b.v1 - b.v0) * s) / 2 + b.v0 * s;
  return {
    ctx: c.ctx, w: c.w, s, ia, ib,
    X: (u) => ox + u * s,
    Y: (w) => oy - w * s,
    ok: (q) => Array.isArray(q) && fin(q[ia]) && fin(q[ib]),
  };
}

// Attempt `a` in view `v` on canvas `c` at clock `t` (frames, fractional), with its readout
// `r` (null: none), in the pair's bounds `b` at scale `s`: layer by layer, bottom first.
function drawAttempt(c, v, a, r, t, b, s) {
  const ctx = c.ctx;
  const dpr = c.dpr || 1;
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, c.w, c.h);
  const g = viewport(c, v, b, s);
  const f = Math.floor(t);
  ctx.lineJoin = 'round';
  ctx.lineCap = 'round';
  drawShapes(g, (a.shapes && a.shapes[v.name]) || []);
  const fr = a.frames;
  drawHead(g, lerpAt(fr.head, t), a.head_radius);
  drawSpoonPath(g, fr.spoon, t);
  if (r) {
    drawEvents(g, fr.spoon, r, f);
    drawClosest(g, fr, r);
  }
  drawArm(g, between(fr.arm, t));
  drawMouth(g, lerpAt(fr.mouth, t), r, t);
  drawSpoon(g, lerpAt(fr.spoon, t), r, f);
  drawFood(g, between(fr.food, t));
}

// The static outlines: furniture under the person.
function drawShapes(g, list) {
  const { ctx, X, Y } = g;
  const shapes = list.slice();
  shapes.sort((x, y) => (x.owner === 'person') - (y.owner === 'person'));
  for (const sh of shapes) {
    const pts = (sh.points || []).filter((q) => Array.isArray(q) && fin(q[0]) && fin(q[1]));
    if (pts.length < 2) continue;
    ctx.beginPath();
    ctx.moveTo(X(pts[0][0]), Y(pts[0][1]));
    for (let i = 1; i < pts.length; i++) ctx.lineTo(X(pts[i][0]), Y(pts[i][1]));
    ctx.closePath();
    const person = sh.owner === 'person';
    ctx.fillStyle = person ? COLORS.personFill : COLORS.furnitureFill;
    ctx.strokeStyle = person ? COLORS.personLine : COLORS.furnitureLine;
    ctx.lineWidth = person ? 1.5 : 1;
    ctx.fill();
    ctx.stroke();
  }
}

// The person's head, a disc of `radius` (metres) at `head`.
function drawHead(g, head, radius) {
  const { ctx, X, Y, ia, ib } = g;
  if (!g.ok(head) || !fin(radius)) return;
  ctx.beginPath();
  ctx.arc(X(head[ia]), Y(head[ib]), Math.max(2, radius * g.s), 0, 2 * Math.PI);
  ctx.fillStyle = COLORS.personFill;
  ctx.strokeStyle = COLORS.personLine;
  ctx.lineWidth = 2;
  ctx.fill();
  ctx.stroke();
}

// The spoon's whole path `sp`, faint from the start; the part up to clock `t` darker.
function drawSpoonPath(g, sp, t) {
  const { ctx, X, Y, ia, ib } = g;
  const path = (upto, style, width) => {
    ctx.beginPath();
    let started = false;
    for (let i = 0; i <= upto && i < sp.length; i++) {
      const q = sp[i];
      if (!g.ok(q)) continue;
      if (!started) { ctx.moveTo(X(q[ia]), Y(q[ib])); started = true; } else ctx.lineTo(X(q[ia]), Y(q[ib]));
    }
    const here = lerpAt(sp, t);
    if (started && upto < sp.length - 1 && g.ok(here)) ctx.lineTo(X(here[ia]), Y(here[ib]));
    ctx.strokeStyle = style;
    ctx.lineWidth = width;
    ctx.stroke();
  };
  path(sp.length - 1, COLORS.path, 2);
  if (t > 0) path(Math.floor(t), COLORS.trailDone, 2.5);
}

// Where contact and spills happened up to frame `f`: a cross on the spoon's path.
function drawEvents(g, sp, r, f) {
  const { ctx, X, Y, ia, ib } = g;
  const mark = (k, color) => {
    const q = sp[k];
    if (!g.ok(q)) return;
    const x = X(q[ia]), y = Y(q[ib]), m = 4.5;
    ctx.beginPath();
    ctx.moveTo(x - m, y - m); ctx.lineTo(x + m, y + m);
    ctx.moveTo(x - m, y + m); ctx.lineTo(x + m, y - m);
    ctx.strokeStyle = color;
    ctx.lineWidth = 2.5;
    ctx.stroke();
  };
  for (const k of r.contact) if (k <= f) mark(k, COLORS.contact);
  for (const k of r.spill) if (k <= f) mark(k, COLORS.spill);
}

// The closest approach in the judged part: a dashed ring where the spoon was, a line to
// the mouth, and the distance.
function drawClosest(g, fr, r) {
  const { ctx, X, Y, ia, ib, s } = g;
  const q = fr.spoon[r.closestAt], m = (fr.mouth || [])[r.closestAt];
  if (!g.ok(q)) return;
  const x = X(q[ia]), y = Y(q[ib]);
  ctx.save();
  ctx.setLineDash([4, 3]);
  ctx.strokeStyle = COLORS.closest;
  ctx.lineWidth = 1.5;
  if (g.ok(m)) {
    ctx.beginPath();
    ctx.moveTo(x, y);
    ctx.lineTo(X(m[ia]), Y(m[ib]));
    ctx.stroke();
  }
  ctx.beginPath();
  ctx.arc(x, y, clamp(0.025 * s, 6, 12) + 4, 0, 2 * Math.PI);
  ctx.stroke();
  ctx.restore();
  // the distance written halfway to the mouth, clear of the spoon
  const [lx, ly] = g.ok(m) ? [(x + X(m[ia])) / 2, (y + Y(m[ib])) / 2 - 10] : [x, y - 24];
  label(ctx, r.nums.distance.closest + ' cm', lx, ly, COLORS.closest, g.w);
}

// The arm at `armPts` (joint origins, then end effector, then spoon): links, then joint dots.
function drawArm(g, armPts) {
  const { ctx, X, Y, ia, ib } = g;
  const lw = clamp(0.022 * g.s, 2.5, 8);
  if (!armPts.length) return;
  const pts = armPts.filter(g.ok);
  if (pts.length > 1) {
    ctx.beginPath();
    ctx.moveTo(X(pts[0][ia]), Y(pts[0][ib]));
    for (let i = 1; i < pts.length; i++) ctx.lineTo(X(pts[i][ia]), Y(pts[i][ib]));
    ctx.strokeStyle = COLORS.arm;
    ctx.lineWidth = lw;
    ctx.stroke();
  }
  const nj = Math.max(0, armPts.length - 2);
  for (let i = 0; i < armPts.length - 1; i++) {
    const q = armPts[i];
    if (!g.ok(q)) continue;
    ctx.beginPath();
    ctx.arc(X(q[ia]), Y(q[ib]), i < nj ? lw * 0.75 : lw * 0.5, 0, 2 * Math.PI);
    ctx.fillStyle = i < nj ? COLORS.joint : COLORS.arm;
    ctx.strokeStyle = COLORS.arm;
    ctx.lineWidth = 1.5;
    ctx.fill();
    ctx.stroke();
  }
}

// The mouth over the head; a green flash for a second when food is eaten.
function drawMouth(g, mouth, r, t) {
  const { ctx, X, Y, ia, ib, s } = g;
  if (!g.ok(mouth)) return;
  const ate = r && r.eaten.some((k) => k <= t && t - k < FPS);
  ctx.beginPath();
  ctx.arc(X(mouth[ia]), Y(mouth[ib]), clamp(0.015 * s, 4, 8), 0, 2 * Math.PI);
  ctx.fillStyle = COLORS.mouth;
  ctx.fill();
  if (ate) {
    ctx.beginPath();
    ctx.arc(X(mouth[ia]), Y(mouth[ib]), clamp(0.015 * s, 4, 8) + 5, 0, 2 * Math.PI);
    ctx.strokeStyle = COLORS.eaten;
    ctx.lineWidth = 3;
    ctx.stroke();
  }
}

// The spoon (a ring, so the food it carries shows inside it), red while it touches the
// person at frame `f`.
function drawSpoon(g, spoon, r, f) {
  const { ctx, X, Y, ia, ib } = g;
  const touching = r && r.series.force[Math.min(f, r.series.force.length - 1)] > CONTACT_N;
  if (!g.ok(spoon)) return;
  const rr = clamp(0.025 * g.s, 6, 12);
  ctx.beginPath();
  ctx.arc(X(spoon[ia]), Y(spoon[ib]), rr, 0, 2 * Math.PI);
  ctx.fillStyle = 'rgba(2,132,199,0.14)';
  ctx.strokeStyle = touching ? COLORS.contact : COLORS.spoon;
  ctx.lineWidth = touching ? 4 : 2.5;
  ctx.fill();
  ctx.stroke();
  if (touching) {
    label(ctx, 'contact ' + r.series.force[f].toFixed(1) + ' N', X(spoon[ia]), Y(spoon[ib]) + rr + 14, COLORS.contact, g.w);
  }
}

// The food particles at `food`.
function drawFood(g, food) {
  const { ctx, X, Y, ia, ib } = g;
  if (!food.length) return;
  const rad = clamp(0.011 * g.s, 3, 6);
  ctx.fillStyle = COLORS.food;
  ctx.strokeStyle = COLORS.foodLine;
  ctx.lineWidth = 1;
  for (const q of food) {
    if (!g.ok(q)) continue;
    ctx.beginPath();
    ctx.arc(X(q[ia]), Y(q[ib]), rad, 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
  }
}

// A short text on a white backing, kept inside the canvas.
function label(ctx, text, x, y, color, width) {
  ctx.save();
  ctx.font = '600 12px system-ui, sans-serif';
  const w = ctx.measureText(text).width;
  const x0 = clamp(x - w / 2, 2, Math.max(2, width - w - 2));
  ctx.fillStyle = 'rgba(255,255,255,0.85)';
  ctx.fillRect(x0 - 3, y - 8, w + 6, 16);
  ctx.fillStyle = color;
  ctx.textBaseline = 'middle';
  ctx.fillText(text, x0, y);
  ctx.restore();
}

// One strip: the quantity over the whole clip on the pair's shared scale, the lead-in
// shaded, the current frame a line.
function drawStrip(st, p, side, t) {
  const ctx = st.ctx;
  const dpr = st.dpr || 1;
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, st.w, st.h);
  const r = p.read[side];
  if (!r) return;
  const n = r.series.distance.length;
  const W = st.w, H = st.h;
  const X = (k) => (n > 1 ? (k / (p.last || 1)) * (W - 2) + 1 : W / 2);
  ctx.fillStyle = '#f9fafb';
  ctx.fillRect(0, 0, W, H);
  if (r.from > 0) {
    ctx.fillStyle = COLORS.leadIn;
    ctx.fillRect(0, 0, X(r.from), H);
  }
  if (st.q === 'food') {
    // stacked: eaten at the bottom, then on the spoon, then spilled; hits as red ticks
    const order = [1, 0, 2];
    const colors = [FOOD_COLORS[1], FOOD_COLORS[0], FOOD_COLORS[2]];
    const bw = Math.max(1, (W - 2) / Math.max(1, p.last));
    for (let k = 0; k < n; k++) {
      let y = H;
      for (let o = 0; o < 3; o++) {
        const hgt = (r.food[k][order[o]] / r.total) * (H - 2);
        ctx.fillStyle = colors[o];
        ctx.globalAlpha = 0.55;
        ctx.fillRect(X(k) - bw / 2, y - hgt, bw + 0.5, hgt);
        y -= hgt;
      }
    }
    ctx.globalAlpha = 1;
    ctx.fillStyle = COLORS.contact;
    for (let k = 1; k < n; k++) if (r.food[k][3] > r.food[k - 1][3]) ctx.fillRect(X(k) - 1, 0, 2, H * 0.45);
  } else {
    const xs = r.series[st.q];
    const top = p.top[st.q] || 1;
    ctx.beginPath();
    for (let k = 0; k < n; k++) {
      const y = H - 2 - (xs[k] / top) * (H - 4);
      if (k === 0) ctx.moveTo(X(k), y); else ctx.lineTo(X(k), y);
    }
    const meta = STRIPS.find((x) => x.q === st.q);
    ctx.strokeStyle = meta.color;
    ctx.lineWidth = 1.5;
    ctx.stroke();
    if (st.q === 'distance') {
      ctx.fillStyle = COLORS.closest;
      ctx.beginPath();
      ctx.arc(X(r.closestAt), H - 2 - (xs[r.closestAt] / top) * (H - 4), 2.5, 0, 2 * Math.PI);
      ctx.fill();
    }
  }
  ctx.fillStyle = '#111827';
  ctx.fillRect(X(t) - 0.75, 0, 1.5, H);
}
