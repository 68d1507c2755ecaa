'use strict';
// The loop inspector. The page holds no data: it takes the key typed in (kept in this tab's
// sessionStorage only), reads the session through loopd's own routes and draws it. Frame ids are
// JavaScript numbers, exact up to 2^53.
(() => {
  const $ = (id) => document.getElementById(id);
  const SVG = 'http://www.w3.org/2000/svg';
  const W = 760, H = 460, PAD = 30;
  const parts = location.pathname.split('/');
  const sessionId = decodeURIComponent(parts[parts.length - 2]);
  const base = '/v1/sessions/' + encodeURIComponent(sessionId);
  const state = { key: '', frames: new Map(), loops: [], selected: null, thumbs: new Map(),
                  edges: new Map(), rows: new Map(), lo: 0, hi: 1, generation: 0, loopConfidence: null };
  const pairKey = (l) => l.query_frame + '-' + l.match_frame;

  function status(text, error) {
    $('status').textContent = text;
    $('status').className = error ? 'error' : '';
  }

  async function api(path, options) {
    const opts = Object.assign({}, options || {});
    opts.headers = Object.assign({ Authorization: 'Bearer ' + state.key }, opts.headers || {});
    const r = await fetch(path, opts);
    if (!r.ok) {
      let msg = r.status + ' ' + r.statusText;
      try { const body = await r.json(); if (body && body.error) msg = r.status + ': ' + body.error; } catch (_) { /* not JSON */ }
      throw new Error(msg);
    }
    return r;
  }

  async function allPages(path, field) {
    const out = [];
    let after = null;
    for (;;) {
      const sep = path.includes('?') ? '&' : '?';
      const page = await (await api(path + (after === null ? '' : sep + 'after=' + encodeURIComponent(after)))).json();
      for (const x of page[field]) out.push(x);
      if (page.next === null || page.next === undefined) return out;
      after = page.next;
    }
  }

  function range(values) {
    let lo = Infinity, hi = -Infinity;
    for (const v of values) { if (v < lo) lo = v; if (v > hi) hi = v; }
    return [lo, hi];
  }

  // Low scores blue, high red, over the session's own score range.
  function colour(score) {
    const t = state.hi > state.lo ? (score - state.lo) / (state.hi - state.lo) : 1;
    return 'hsl(' + Math.round(220 - 220 * Math.min(1, Math.max(0, t))) + ',75%,45%)';
  }

  function robotColour(i) { return 'hsl(' + ((i * 137) % 360) + ',35%,40%)'; }

  function el(name, attrs, parent) {
    const e = document.createElementNS(SVG, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (parent) parent.appendChild(e);
    return e;
  }

  // Where each frame is drawn: a top view of the poses (the two widest axes), or, without
  // poses, one row per robot along time.
  function layout(frames, robots) {
    const pos = new Map();
    const posed = frames.filter((f) => f.pose);
    if (posed.length >= 2) {
      const axes = ['x', 'y', 'z'].map((a) => { const [lo, hi] = range(posed.map((f) => f.pose[a])); return { a, lo, hi }; });
      axes.sort((p, q) => (q.hi - q.lo) - (p.hi - p.lo));
      const [u, v] = axes;
      const s = Math.min((W - 2 * PAD) / ((u.hi - u.lo) || 1), (H - 2 * PAD) / ((v.hi - v.lo) || 1));
      for (const f of posed) pos.set(f.frame_id, [PAD + (f.pose[u.a] - u.lo) * s, H - PAD - (f.pose[v.a] - v.lo) * s]);
      return { pos, mode: 'poses', note: 'Top view of the poses: ' + u.a + ' to the right, ' + v.a + ' up. ' +
        (frames.length - posed.length) + ' frames without a pose are not drawn.' };
    }
    const [lo, hi] = range(frames.map((f) => f.timestamp));
    const rowH = (H - 2 * PAD) / Math.max(1, robots.length);
    for (const f of frames) {
      const x = PAD + (hi > lo ? (f.timestamp - lo) / (hi - lo) : 0.5) * (W - 2 * PAD);
      pos.set(f.frame_id, [x, PAD + rowH * (robots.indexOf(f.robot_id) + 0.5)]);
    }
    return { pos, mode: 'timeline', rowH, note: 'No poses: one row per robot along time; loops are the arcs.' };
  }

  function drawMap() {
    const svg = $('map');
    svg.replaceChildren();
    state.edges.clear();
    const frames = [...state.frames.values()];
    const robots = [...new Set(frames.map((f) => f.robot_id))].sort();
    const { pos, mode, rowH, note } = layout(frames, robots);
    robots.forEach((robot, i) => {
      const own = frames.filter((f) => f.robot_id === robot && pos.has(f.frame_id))
        .sort((a, b) => a.timestamp - b.timestamp || a.frame_id - b.frame_id);
      if (!own.length) return;
      const points = own.map((f) => pos.get(f.frame_id).map((c) => c.toFixed(1)).join(',')).join(' ');
      el('polyline', { class: 'trajectory', points, stroke: robotColour(i), 'data-robot': robot,
                       'data-points': own.length }, svg);
      const [x, y] = pos.get(own[0].frame_id);
      el('text', { class: 'robot-label', x: x + 4, y: y - 6 }, svg).textContent = robot;
    });
    for (const l of state.loops) {
      const a = pos.get(l.query_frame), b = pos.get(l.match_frame);
      if (!a || !b) continue;
      let shape;
      if (mode === 'timeline' && Math.abs(a[1] - b[1]) < 1) {
        const lift = Math.min(rowH * 0.45, Math.abs(a[0] - b[0]) / 2 + 8);
        const d = 'M' + a[0].toFixed(1) + ',' + a[1].toFixed(1) + ' Q' + ((a[0] + b[0]) / 2).toFixed(1) + ',' +
          (a[1] - 2 * lift).toFixed(1) + ' ' + b[0].toFixed(1) + ',' + b[1].toFixed(1);
        shape = el('path', { d }, svg);
      } else {
        shape = el('line', { x1: a[0], y1: a[1], x2: b[0], y2: b[1] }, svg);
      }
      shape.setAttribute('class', 'loop');
      shape.setAttribute('stroke', colour(l.score));
      shape.dataset.q = l.query_frame;
      shape.dataset.m = l.match_frame;
      shape.dataset.score = l.score;
      el('title', {}, shape).textContent = l.query_frame + ' → ' + l.match_frame + ' score ' + l.score.toFixed(3);
      shape.addEventListener('click', () => select(l));
      state.edges.set(pairKey(l), shape);
    }
    $('map-note').textContent = note;
    $('legend').textContent = 'colour: score ' + state.lo.toFixed(2) + ' (blue) … ' + state.hi.toFixed(2) + ' (red)';
  }

  function frameText(robot, id, t) { return robot + ' #' + id + ' · t=' + Number(t).toFixed(2); }

  function verdictText(l) { return l.verdict ? (l.verdict.accepted ? 'accepted' : 'rejected') : ''; }

  function confidenceText(l) {
    return typeof l.confidence === 'number' ? l.confidence.toFixed(3) : '—';
  }

  // A loop by the server's calibrated confidence: at least its loop confidence (/v1/info).
  function isLoop(l) {
    return state.loopConfidence === null || (typeof l.confidence === 'number' && l.confidence >= state.loopConfidence);
  }

  function verifiedText(l) {
    if (!l.checked) return '—';
    return (l.verified ? '✓ ' : '✗ ') + l.inliers + ' inliers';
  }

  function decorate(l) {
    const cls = verdictText(l);
    const row = state.rows.get(pairKey(l));
    if (row) {
      row.classList.remove('accepted', 'rejected');
      if (cls) row.classList.add(cls);
      row.cells[4].textContent = cls;
    }
    const edge = state.edges.get(pairKey(l));
    if (edge) {
      edge.classList.remove('accepted', 'rejected');
      if (cls) edge.classList.add(cls);
    }
  }

  function drawTable() {
    const body = $('loops').tBodies[0];
    body.replaceChildren();
    state.rows.clear();
    for (const l of state.loops) {
      const row = body.insertRow();
      row.className = 'loop-row';
      row.dataset.q = l.query_frame;
      row.dataset.m = l.match_frame;
      row.dataset.score = l.score;
      row.dataset.loop = isLoop(l);
      const cells = [frameText(l.query_robot, l.query_frame, l.query_time),
                     frameText(l.match_robot, l.match_frame, l.match_time),
                     l.score.toFixed(3), verifiedText(l), '', confidenceText(l)];
      for (const c of cells) row.insertCell().textContent = c;
      row.addEventListener('click', () => select(l));
      state.rows.set(pairKey(l), row);
      decorate(l);
    }
  }

  function applyThreshold() {
    const t = Number($('threshold').value);
    const onlyLoops = $('only-loops').checked;
    $('threshold-value').textContent = t.toFixed(2);
    let shown = 0;
    for (const l of state.loops) {
      const hide = l.score < t || (onlyLoops && !isLoop(l));
      if (!hide) shown++;
      const row = state.rows.get(pairKey(l)), edge = state.edges.get(pairKey(l));
      if (row) row.classList.toggle('hidden', hide);
      if (edge) edge.classList.toggle('hidden', hide);
    }
    $('loops-panel').querySelector('h2').textContent = 'Kept loops (' + shown + ' of ' + state.loops.length + ' shown)';
  }

  // A thumbnail as a blob URL (fetched with the key), or null when the frame has none.
  async function thumb(id) {
    if (state.thumbs.has(id)) return state.thumbs.get(id);
    let url = null;
    try {
      const r = await api(base + '/frames/' + id + '/thumbnail');
      url = URL.createObjectURL(await r.blob());
    } catch (_) { url = null; }
    state.thumbs.set(id, url);
    return url;
  }

  async function showThumb(img, id, caption) {
    const url = await thumb(id);
    if (!url) {
      img.removeAttribute('src');
      img.dataset.missing = 'true';
      caption.textContent += ' · no thumbnail';
      return false;
    }
    delete img.dataset.missing;
    img.src = url;
    try { await img.decode(); return true; } catch (_) { return false; }
  }

  function drawInliers(l, both) {
    const canvas = $('inliers'), pair = $('pair');
    const qi = $('thumb-query'), mi = $('thumb-match');
    canvas.width = pair.clientWidth;
    canvas.height = pair.clientHeight;
    const g = canvas.getContext('2d');
    g.clearRect(0, 0, canvas.width, canvas.height);
    const matches = both ? (l.inlier_matches || []) : [];
    g.strokeStyle = 'rgba(0, 200, 90, 0.8)';
    g.lineWidth = 1;
    for (const m of matches) {
      const x1 = qi.offsetLeft + m[0] * qi.width, y1 = qi.offsetTop + m[1] * qi.height;
      const x2 = mi.offsetLeft + m[2] * mi.width, y2 = mi.offsetTop + m[3] * mi.height;
      g.beginPath(); g.moveTo(x1, y1); g.lineTo(x2, y2); g.stroke();
      g.beginPath(); g.arc(x1, y1, 2, 0, 2 * Math.PI); g.arc(x2, y2, 2, 0, 2 * Math.PI); g.stroke();
    }
    canvas.dataset.lines = matches.length;
  }

  function facts(l) {
    const dl = $('facts');
    dl.replaceChildren();
    const add = (k, v) => {
      const dt = document.createElement('dt'); dt.textContent = k; dl.appendChild(dt);
      const dd = document.createElement('dd'); dd.textContent = v; dl.appendChild(dd);
    };
    add('score', l.score.toFixed(4) + ' (rank ' + l.rank + ')');
    add('confidence', confidenceText(l) + (isLoop(l) ? ' (a loop)' : ' (below the loop confidence)'));
    add('query', frameText(l.query_robot, l.query_frame, l.query_time));
    add('match', frameText(l.match_robot, l.match_frame, l.match_time));
    add('Δt', (l.query_time - l.match_time).toFixed(2) + ' s');
    add('geometry', l.checked ? verifiedText(l) + ((l.inlier_matches || []).length ? ' (green: inlier matches)' : '')
      : 'not checked');
    if (l.relative_pose) {
      const p = l.relative_pose, t = [p.tx, p.ty, p.tz];
      const q = ' · q ' + [p.qx, p.qy, p.qz, p.qw].map((v) => v.toFixed(3)).join(' ');
      if (l.metric) {
        const norm = Math.hypot(p.tx, p.ty, p.tz);
        add('relative pose', 't ' + t.map((v) => v.toFixed(3)).join(' ') + ' m (' + norm.toFixed(3) + ' m)' + q);
        const c = l.covariance || [];
        if (c.length === 36) {
          // Standard deviations: the covariance's diagonal (x y z in m², rotation vector in rad²).
          const sd = (i) => Math.sqrt(Math.max(0, c[i * 7]));
          add('σ', 't ' + [0, 1, 2].map((i) => (100 * sd(i)).toFixed(2)).join(' ') + ' cm · rotation ' +
            [3, 4, 5].map((i) => (sd(i) * 180 / Math.PI).toFixed(2)).join(' ') + '°');
        }
      } else {
        add('relative pose', 'direction ' + t.map((v) => v.toFixed(3)).join(' ') + ' (monocular: scale unknown)' + q);
      }
    }
    add('found', new Date(l.found * 1000).toISOString());
    add('verdict', l.verdict ? verdictText(l) + ' at ' + new Date(l.verdict.at * 1000).toISOString() +
      (l.verdict.relative_pose ? ' (with a registration)' : '') : 'none yet');
  }

  async function select(l) {
    state.selected = l;
    for (const e of document.querySelectorAll('.selected')) e.classList.remove('selected');
    const row = state.rows.get(pairKey(l)), edge = state.edges.get(pairKey(l));
    if (row) row.classList.add('selected');
    if (edge) edge.classList.add('selected');
    $('detail-title').textContent = l.query_frame + ' → ' + l.match_frame;
    $('cap-query').textContent = 'query ' + frameText(l.query_robot, l.query_frame, l.query_time);
    $('cap-match').textContent = 'match ' + frameText(l.match_robot, l.match_frame, l.match_time);
    facts(l);
    $('accept').disabled = false;
    $('reject').disabled = false;
    $('verdict-status').textContent = '';
    $('inliers').dataset.lines = '';
    const [a, b] = await Promise.all([showThumb($('thumb-query'), l.query_frame, $('cap-query')),
      showThumb($('thumb-match'), l.match_frame, $('cap-match'))]);
    if (state.selected === l) drawInliers(l, a && b);
  }

  async function verdict(accepted) {
    const l = state.selected;
    if (!l) return;
    const body = { accepted };
    // Accepting again keeps a registration a back end gave with its own verdict.
    if (accepted && l.verdict && l.verdict.relative_pose) {
      body.relative_pose = l.verdict.relative_pose;
      if (l.verdict.covariance) body.covariance = l.verdict.covariance;
    }
    try {
      const r = await api(base + '/loops/' + l.query_frame + '/' + l.match_frame + '/verdict', {
        method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) });
      const updated = await r.json();
      Object.assign(l, updated);
      decorate(l);
      facts(l);
      $('verdict-status').textContent = (accepted ? 'accepted' : 'rejected') + ' (saved)';
    } catch (e) {
      $('verdict-status').textContent = 'not saved: ' + e.message;
    }
  }

  async function drawSimilarity() {
    const canvas = $('similarity');
    const size = Math.min(256, Math.max(1, state.frames.size));
    const m = await (await api(base + '/similarity?size=' + size)).json();
    const n = m.frame_ids.length;
    const off = document.createElement('canvas');
    off.width = n; off.height = n;
    if (n > 0) {
      const g = off.getContext('2d');
      const img = g.createImageData(n, n);
      const [lo] = range(m.values);
      for (let i = 0; i < n * n; i++) {
        const t = lo < 1 ? Math.max(0, (m.values[i] - lo) / (1 - lo)) : 1;
        const v = Math.round(255 * Math.pow(t, 2));
        img.data.set([v, Math.round(v * 0.85), Math.round(255 * t * (1 - t)), 255], i * 4);
      }
      g.putImageData(img, 0, 0);
    }
    const g = canvas.getContext('2d');
    g.imageSmoothingEnabled = false;
    g.clearRect(0, 0, canvas.width, canvas.height);
    if (n > 0) g.drawImage(off, 0, 0, canvas.width, canvas.height);
    canvas.dataset.size = n;
    $('similarity-note').textContent = n + ' of ' + state.frames.size + ' frames, evenly along the frame ids ' +
      '(row and column order); brighter is more alike; revisits show as streaks off the diagonal.';
  }

  async function load() {
    // Only the newest load draws (the key may be submitted again while one runs).
    const generation = ++state.generation;
    document.body.dataset.loaded = 'false';
    status('Loading ' + sessionId + ' …');
    try {
      const info = await (await api(base)).json();
      const server = await (await api('/v1/info')).json();
      const frames = await allPages(base + '/frames?limit=10000', 'frames');
      const loops = await allPages(base + '/loops?limit=1000', 'loops');
      if (generation !== state.generation) return;
      $('session-name').textContent = info.name ? info.name + ' (' + info.id + ')' : info.id;
      state.frames = new Map(frames.map((f) => [f.frame_id, f]));
      state.loops = loops;
      // Without a calibrated confidence every kept candidate is shown.
      state.loopConfidence = typeof server.loop_confidence === 'number' ? server.loop_confidence : null;
      $('only-loops').disabled = state.loopConfidence === null;
      $('loop-confidence').textContent = state.loopConfidence === null ? 'none (no calibrator)' : state.loopConfidence.toFixed(2);
      [state.lo, state.hi] = state.loops.length ? range(state.loops.map((l) => l.score)) : [0, 1];
      const slider = $('threshold');
      slider.min = (Math.floor(state.lo * 100) / 100).toFixed(2);
      slider.value = slider.min;
      drawMap();
      drawTable();
      applyThreshold();
      await drawSimilarity();
      if (generation !== state.generation) return;
      const robots = new Set(frames.map((f) => f.robot_id)).size;
      status(frames.length + ' frames of ' + robots + ' robot(s), ' + state.loops.length + ' kept loops' +
        (info.thumbnails ? '' : ' (this session keeps no thumbnails)'));
      document.body.dataset.loaded = 'true';
    } catch (e) {
      if (generation !== state.generation) return;
      status('Could not load the session: ' + e.message, true);
      document.body.dataset.loaded = 'error';
    }
  }

  document.addEventListener('DOMContentLoaded', () => {
    $('key-form').addEventListener('submit', (ev) => {
      ev.preventDefault();
      state.key = $('key').value.trim();
      sessionStorage.setItem('loopd-key', state.key);
      load();
    });
    $('threshold').addEventListener('input', applyThreshold);
    $('only-loops').addEventListener('change', applyThreshold);
    $('accept').addEventListener('click', () => verdict(true));
    $('reject').addEventListener('click', () => verdict(false));
    const kept = sessionStorage.getItem('loopd-key');
    if (kept) {
      $('key').value = kept;
      state.key = kept;
      load();
    }
  });
})();
