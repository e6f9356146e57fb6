// Forja's operator page. One WebSocket (/ws) carries the link's own protocols (docs/protocol.md):
// RepRap G-code lines and their Marlin-style replies, and the 53-byte frames. Nothing here is
// a second API: every button sends what a host on the serial or TCP link would send.
//
//   position, progress, keep-alive   frames 04 51 and 04 52 every 500 ms (answered at once in
//                                    every state); no answer for 3 s: "connection lost"
//   start, pause, resume, stop,      frames 02 Start, Pause, Start, Stop, Rewind, Reset
//   rewind, reset
//   emergency stop                   M112
//   jog, home                        G91 / G1 <axis><step> F<feed> / G90 (as printer hosts jog),
//                                    G28
//   upload                           frames 03 (the program store), ten at a time, each batch
//                                    checked with 04 52; or M28 <name> … M29 (the SD card)
//   file list, select, run, delete   M20, M23, M23 + M24, M30 <name>; the stored program after
//                                    a file: M22 + M21 (the card released), then frame Start
//   temperatures                     M105 every second; M104 / M140 / M141 S<target>
//   settings, WiFi                   frames 00 (key to read, key=value to set; link.ssid,
//                                    link.password)
//   who controls                     the server's first line: `// control: …`, or `// watching:
//                                    …` for a second client, which then sees the controller's
//                                    traffic, sends nothing, and has its controls disabled
//                                    until it is sent `// control: …` (the controller left).
'use strict';

(() => {
  const $ = (id) => document.getElementById(id);
  const now = () => performance.now();

  // ---- Frames (docs/protocol.md §4) ----------------------------------------------------

  const PAYLOAD = 49;
  const stars = (n) => '*'.repeat(Math.max(0, n));
  const d4 = (n) => String(n).padStart(4, '0');
  const frame = (type, payload) => 'N' + type + payload + stars(PAYLOAD - payload.length) + 'F';
  const actionFrame = (kw) => 'N02' + kw + stars(PAYLOAD - 2 * kw.length) + kw + 'F';
  const requestFrame = (t) => 'N04' + t + stars(45) + t + 'F';
  const loadFrame = (i, text, total) =>
    'N03' + d4(i) + 'C' + text + stars(39 - text.length) + 'f' + d4(total) + 'F';
  const isFrame = (r) => r.length === 53 && /^N\d\d[ -~]{49}F$/.test(r);
  const payloadText = (r) => r.slice(3, 52).replace(/\*+$/, '');
  const mmss = (t) => {
    const [m, s] = t.split(':');
    return +m * 60 + +s;
  };

  // ---- What the controller's codes mean (docs/protocol.md §5, motion/src/error.rs) ------

  const MEANING = {
    120: 'the controller does not have this command',
    121: 'a value is out of range',
    122: 'a value is missing',
    123: "the arc's end is not on its circle",
    124: 'the move ends outside the travel',
    125: 'the machine is in alarm: reset or home it',
    126: 'the machine is halted: reset it',
    127: 'no such axis on this machine',
    128: 'the machine must be at rest for this',
    131: 'the move is longer than the axis',
    150: 'a limit switch tripped',
    151: 'homing did not find its switch',
    152: 'the homing switch stayed triggered',
    153: 'emergency stop',
    170: 'a program line arrived out of order',
    171: 'the program store is full',
    172: 'a program line is longer than 39 bytes',
    175: 'no upload in progress: upload the program again',
    176: 'no such file',
    177: 'the card is full',
    178: 'the card does not take that name',
    179: 'a file is being written already',
    180: 'no program is stored: upload one',
    181: 'no job is running',
    182: 'a job is running: stop it first',
    183: 'a program line failed and the job stopped',
    185: 'the stored program is incomplete: upload it again',
    189: 'no file is selected',
    190: 'no such setting',
    191: 'the value is not valid',
    194: 'the machine has no such device',
    195: 'a value the device cannot take',
    197: 'the receive queue was full',
    198: 'the line was dropped by a stop',
    210: 'heater fault',
    211: 'heater fault',
    212: 'heater fault (thermal runaway)',
    213: 'heater fault (over temperature)',
    214: 'heater fault',
    300: 'another host controls the machine',
  };
  const FAULTS = (c) => (c >= 150 && c <= 158) || (c >= 210 && c <= 214);
  const FATAL_UPLOAD = [125, 126, 128, 171, 172, 174, 175, 182, 185];
  const explain = (code, text) => {
    const m = MEANING[code];
    return m ? `${m} (E${code} ${text})` : `E${code} ${text}`;
  };

  // ---- G-code lines as the firmware reads them (docs/protocol.md §2) ---------------------

  // Commands whose argument is free text (§2.3).
  const TEXT_COMMANDS = ['M23', 'M28', 'M29', 'M30', 'M32', 'M117', 'M118'];
  const MAX_WORDS = 20;

  // One source line: its words ({l, v, raw}) and free text; null when there is no G-code on
  // it. Throws a reason for a line the firmware would refuse.
  function parseLine(src) {
    const words = [];
    let text = null;
    let i = 0;
    const s = src.replace(/\r$/, '');
    while (i < s.length) {
      const c = s[i];
      if (c === ' ' || c === '\t') {
        i++;
        continue;
      }
      if (c === ';') break;
      if (c === '(') {
        const end = s.indexOf(')', i);
        if (end < 0) throw 'a "(" comment that is not closed';
        i = end + 1;
        continue;
      }
      if (c === '*') throw 'a checksum (*): send the file without line numbers and checksums';
      if (!/[A-Za-z]/.test(c)) throw `"${c}" cannot start a G-code word (a letter and a number)`;
      const l = c.toUpperCase();
      const rest = s.slice(i + 1);
      const m = /^[+-]?(\d+\.?\d*|\.\d+)/.exec(rest);
      if (!m) {
        if (/^[ \t]+[+\-.\d]/.test(rest)) throw `a space between ${l} and its number`;
        words.push({ l, v: '' }); // a bare letter (G28 X Y)
        i++;
        continue;
      }
      words.push({ l, v: m[0] });
      i += 1 + m[0].length;
      if (words.length === 1 || (words.length === 2 && words[0].l === 'N')) {
        const cmd = l + String(+m[0]);
        if (TEXT_COMMANDS.includes(cmd)) {
          const rest = s.slice(i).split(/[;*]/)[0].trim();
          text = rest || null;
          break;
        }
      }
    }
    // A leading N word (CAM posts number their lines) is the link's business, not the program's.
    if (words.length && words[0].l === 'N') words.shift();
    if (!words.length && text === null) return null;
    if (words.length > MAX_WORDS) throw `more than ${MAX_WORDS} words on one line`;
    if (words.some((w) => w.l === 'M' && +w.v === 110)) {
      throw 'M110 sets line numbers, which the link manages; remove the line';
    }
    return { words, text };
  }

  // The shortest text that reads as the same number.
  function shortest(v) {
    let t = v.replace(/^\+/, '');
    if (t.includes('.')) t = t.replace(/0+$/, '').replace(/\.$/, '');
    t = t.replace(/^(-?)0+(?=\d)/, '$1').replace(/^(-?)0\./, '$1.');
    return t === '' || t === '-' ? '0' : t;
  }
  function compact(p, short) {
    let out = p.words
      .map((w) => w.l + (short ? (w.v === '' ? '' : shortest(w.v)) : w.v.replace(/^\+/, '')))
      .join('');
    if (p.text !== null) out += ' ' + p.text;
    return out;
  }

  // A G-code file as the page sends it: its lines (compact, comments dropped) with their
  // source line numbers, and each line parsed. Throws "line N: reason".
  function compile(text, frameTexts) {
    const lines = [];
    const src = text.split('\n');
    if (src.length && src[src.length - 1] === '') src.pop();
    src.forEach((raw, k) => {
      let p;
      try {
        if (/[^\t\r -~]/.test(raw.split(';')[0])) throw 'a character outside printable ASCII';
        p = parseLine(raw);
      } catch (why) {
        throw `line ${k + 1}: ${why}`;
      }
      if (!p) return;
      let t = compact(p, false);
      if (frameTexts && t.length > 39) t = compact(p, true);
      if (frameTexts && t.length > 39) {
        throw (
          `line ${k + 1}: "${t}" is ${t.length} bytes; ` +
          'a stored program line holds 39: split the move'
        );
      }
      if (t.includes('*')) throw `line ${k + 1}: a "*" in its text`;
      if (t.length > 240) throw `line ${k + 1}: longer than a G-code line may be`;
      lines.push({ text: t, src: k + 1, p });
    });
    if (!lines.length) throw 'the file has no G-code lines';
    return lines;
  }

  // ---- The model ------------------------------------------------------------------------

  const m = {
    ws: null,
    link: 'connecting', // connecting | up | lost
    role: 'unknown', // unknown | control | watch
    machine: '',
    sd: false,
    axes: [], // [{ l, mm }]
    prog: { el: 0, es: 0, nl: 0, la: 0 },
    elapsedAt: -1e9,
    laAt: -1e9,
    movedAt: -1e9,
    lastRx: 0,
    intent: null,
    intentAt: -1e9, // run | pause | null: what this page last asked
    alarm: null,
    homing: false,
    heaters: {},
    tempHist: [],
    tempPolling: false,
    program: null, // { stored, total, complete }
    files: [],
    selected: null, // a file name selected with M23, else the program runs
    preview: null, // { name, segs, bounds, lines }
    uploading: false, // an upload is under way (the page's own)
    uploadingFrames: false, // frames 03 go out: no G-code line and no poll meanwhile
    uploadErrors: [], // the 56 answers that came meanwhile
    tempBusy: false,
  };

  // ---- The link -------------------------------------------------------------------------

  let rxBuf = '';
  const WINDOW = 480; // bytes of G-code in flight, within the controller's 768-byte read-ahead
  const gq = { queue: [], flight: [], bytes: 0 };
  const want51 = [],
    want52 = [],
    want50 = [];

  function connect() {
    const url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws';
    let ws;
    try {
      ws = new WebSocket(url);
    } catch (e) {
      setTimeout(connect, 2000);
      return;
    }
    m.ws = ws;
    m.link = 'connecting';
    m.role = 'unknown';
    rxBuf = '';
    ws.onopen = () => {
      m.lastRx = now();
      // The watch notice, when this client is not in control, is the first thing it gets.
      setTimeout(() => {
        if (m.ws === ws && m.role === 'unknown') becomeController();
      }, 400);
      render();
    };
    ws.onmessage = (ev) => receive(String(ev.data));
    ws.onclose = () => {
      if (m.ws !== ws) return;
      m.ws = null;
      m.link = 'lost';
      failAll('the connection was lost');
      render();
      setTimeout(connect, 2000);
    };
    ws.onerror = () => {};
  }

  function raw(text) {
    if (m.ws && m.ws.readyState === 1 && m.role !== 'watch') m.ws.send(text);
  }

  function failAll(why) {
    for (const e of gq.flight.concat(gq.queue)) e.done({ ok: false, lines: [], error: why });
    gq.queue = [];
    gq.flight = [];
    gq.bytes = 0;
    for (const q of [want51, want52, want50]) while (q.length) q.shift().done(null);
    m.homing = false;
    m.tempPolling = false;
  }

  // Send a G-code line; resolves with { ok, lines, error } once its terminal `ok` came.
  function gcode(line, opts = {}) {
    return new Promise((done) => {
      if (m.role !== 'control') {
        done({ ok: false, lines: [], error: 'this page does not control the machine' });
        return;
      }
      gq.queue.push({ line, auto: !!opts.auto, done, lines: [], error: null });
      if (!opts.auto) logLine('> ' + line, 'tx');
      pump();
    });
  }
  function pump() {
    let out = '';
    while (gq.queue.length && !m.uploadingFrames) {
      const e = gq.queue[0];
      const n = e.line.length + 1;
      if (gq.flight.length && gq.bytes + n > WINDOW) break;
      gq.queue.shift();
      gq.flight.push(e);
      gq.bytes += n;
      out += e.line + '\n';
    }
    if (out) raw(out);
  }
  // Frame 04 after `before` (other frames): resolves with the answer (null when the link
  // went away). The controller answers requests in order.
  function request(type, before = '') {
    return new Promise((done) => {
      (type === '51' ? want51 : want52).push({ done, at: now() });
      raw(before + requestFrame(type) + '\n');
    });
  }
  const waitFor = (p, ms) => Promise.race([p, new Promise((r) => setTimeout(() => r(null), ms))]);

  function receive(text) {
    m.lastRx = now();
    rxBuf += text;
    let k;
    while ((k = rxBuf.indexOf('\n')) >= 0) {
      const line = rxBuf.slice(0, k).replace(/\r$/, '');
      rxBuf = rxBuf.slice(k + 1);
      if (line) onLine(line);
    }
    if (rxBuf.length > 4096) rxBuf = '';
    scheduleRender();
  }

  // The server's first line says who controls: `// control: …` or `// watching: …`; a
  // watcher is sent `// control: …` when the controller it watched left.
  function onLine(line) {
    if (/^\/\/ control:/.test(line)) {
      logLine(line, 'note');
      becomeController();
      return;
    }
    if (/^\/\/ watching:/.test(line)) {
      becomeWatcher(line);
      return;
    }
    if (m.role === 'unknown') becomeController();
    if (isFrame(line)) {
      onFrame(line);
      return;
    }
    const head = gq.flight[0];
    const mine = m.role === 'control' && head;
    // The answers to the page's own polls stay out of the console; faults and notices never do.
    const quiet =
      !/^(Error:|!!|\/\/ )/.test(line) &&
      ((mine ? head.auto : /^ok\b|^ ?T\d?:|^X:-?\d/.test(line)) ||
        line === 'echo:busy: processing');
    if (!quiet || $('console-all').checked)
      logLine(
        line,
        /^(Error:|echo:E\d|echo:Unknown|open failed|Deletion failed|!!)/.test(line) ? 'err' : '',
      );
    if (/^ok\b/.test(line)) {
      temperatures(line);
      if (mine) {
        gq.flight.shift();
        gq.bytes -= head.line.length + 1;
        head.done({ ok: !head.error, lines: head.lines, error: head.error });
        pump();
      }
      return;
    }
    if (/^ ?(T\d?|B|C):-?\d/.test(line)) {
      temperatures(line);
      return;
    }
    if (line.startsWith('Error:')) {
      fault(line.slice(6));
      return;
    }
    if (line === 'start') {
      m.alarm = null;
      failAll('the controller restarted');
      if (m.role === 'control') greet();
      return;
    }
    if (/^\/\/ action:notification Machine halted/.test(line)) {
      m.alarm = line.replace(/^.*halted: /, '');
      return;
    }
    if (mine) {
      head.lines.push(line);
      const r =
        /^echo:(E(\d+) (.*)|Unknown command: .*|No media|SD init fail)$/.exec(line) ||
        /^(open failed|Deletion failed), File: .*$/.exec(line);
      if (r && !head.error) head.error = r[2] ? explain(+r[2], r[3]) : r[1];
    }
  }

  function onFrame(r) {
    const type = r.slice(1, 3);
    const p = r.slice(3, 52);
    if (type === '51' || type === '01') {
      const axes = [];
      for (let i = 0; i < 4; i++) {
        const c = p.substr(1 + 12 * i, 12);
        if (!/^[+-]\d{5}\.\d{4}[a-z]$/.test(c)) break;
        axes.push({ l: c[11].toUpperCase(), mm: parseFloat(c.slice(0, 11)) });
      }
      if (
        m.axes.length !== axes.length ||
        axes.some((a, i) => Math.abs(a.mm - m.axes[i].mm) > 0.00005)
      ) {
        if (m.axes.length === axes.length) m.movedAt = now();
        m.axes = axes;
        drawPreviewSoon();
      }
      const w = want51.shift();
      if (w) w.done(axes);
    } else if (type === '52' || type === '02') {
      const g = {
        el: mmss(p.substr(2, 5)),
        es: mmss(p.substr(9, 5)),
        nl: +p.substr(16, 4),
        la: +p.substr(22, 4),
      };
      if (g.el !== m.prog.el) m.elapsedAt = now();
      if (g.la !== m.prog.la) {
        m.laAt = now();
        drawPreviewSoon();
      }
      m.prog = g;
      const w = want52.shift();
      if (w) w.done(g);
    } else if (type === '50') {
      const t = payloadText(r);
      const eq = t.indexOf('=');
      const key = eq < 0 ? t : t.slice(0, eq);
      const value = eq < 0 ? '' : t.slice(eq + 1);
      const k = want50.findIndex((w) => w.key.toLowerCase() === key.toLowerCase());
      if (k >= 0) want50.splice(k, 1)[0].done({ key, value });
      showSetting(key, value);
    } else if (type === '53') {
      logLine('controller: ' + payloadText(r), 'note');
    } else if (type === '56') {
      const t = payloadText(r).replace(/^Error:/, '');
      const c = /^E(\d+) ?(.*)$/.exec(t);
      const code = c ? +c[1] : 0;
      const text = c ? explain(code, c[2]) : t;
      // A setting this machine lacks (an axis without homing) answers a read: not news.
      if ((code === 190 || code === 191 || code === 128 || code >= 230) && want50.length) {
        const w = want50.shift();
        if (w.write) logLine('controller: ' + text, 'err');
        w.done({ error: text });
        return;
      }
      logLine('controller: ' + text, 'err');
      if (FAULTS(code)) {
        fault(t);
        return;
      }
      if (m.uploadingFrames) {
        m.uploadErrors.push({ code, text });
        return;
      }
      if (m.intent && now() - m.intentAt < 2000) m.intent = null;
      say(text, true);
    }
  }

  // A fault that stopped the machine (`Error:E150 hard-limit X`, or its frame 56).
  function fault(text) {
    const c = /^E(\d+) ?(.*)$/.exec(text);
    m.alarm = c ? explain(+c[1], c[2]) : text;
    m.intent = null;
    say(`Machine stopped: ${m.alarm}. Reset it, or home it.`, true);
  }

  function becomeWatcher(line) {
    m.role = 'watch';
    m.link = 'up';
    logLine(line, 'note');
    render();
  }

  function becomeController() {
    if (m.role === 'control') return;
    m.role = 'control';
    m.link = 'up';
    greet();
    render();
  }

  // What the page asks once it controls the link.
  async function greet() {
    const id = await gcode('M115', { auto: true });
    for (const l of id.lines) {
      const t = /MACHINE_TYPE:(\S+)/.exec(l);
      if (t) m.machine = t[1];
      if (/^Cap:SDCARD:1/.test(l)) m.sd = true;
    }
    const temps = await gcode('M105', { auto: true });
    m.tempPolling = temps.ok && Object.keys(m.heaters).length > 0;
    await listFiles();
    await readSettings();
    render();
  }

  // ---- Polls: the keep-alive --------------------------------------------------------------

  // The connection is lost when a request sent has had no answer for 3 s (not when no request
  // went out: a browser slows the timers of a page in the background).
  let pollsOut = 0;
  setInterval(() => {
    const t = now();
    if (!m.ws || m.ws.readyState !== 1) return;
    if (m.role === 'control') {
      const waited = want52.length ? t - want52[0].at : 0;
      if (waited > 3000) m.link = 'lost';
      if (waited > 8000) {
        m.ws.close();
        return;
      }
      if (!m.uploadingFrames && pollsOut < 4) {
        pollsOut++;
        Promise.all([request('51'), request('52')]).then((a) => {
          pollsOut--;
          if (a[0] && a[1]) m.link = 'up';
        });
      }
    } else if (m.role === 'watch') {
      m.link = t - m.lastRx > 5000 ? 'lost' : 'up';
    }
    render();
  }, 500);

  setInterval(async () => {
    if (m.role !== 'control' || !m.tempPolling || m.tempBusy || m.uploadingFrames) return;
    m.tempBusy = true;
    await gcode('M105', { auto: true });
    m.tempBusy = false;
  }, 1000);

  // ---- Machine state, as far as the controller shows it ---------------------------------

  function jobTicking() {
    return now() - m.elapsedAt < 1700;
  }
  function recentIntent() {
    return now() - m.intentAt < 1500;
  }
  function moving() {
    return now() - m.movedAt < 800;
  }

  function machineState() {
    if (m.link === 'connecting') return 'connecting';
    if (m.link === 'lost') return 'lost';
    if (m.alarm) return 'alarm';
    if (m.homing) return 'homing';
    const p = m.prog;
    const active = jobTicking() || (m.intent && recentIntent());
    if (active) {
      if (m.intent === 'pause') return moving() ? 'pausing' : 'paused';
      if (m.intent === 'run') return 'running';
      return moving() || now() - m.laAt < 3000 ? 'running' : 'held';
    }
    if (m.intent) m.intent = null;
    if (p.nl > 0 && p.la === p.nl && p.el > 0) return 'finished';
    return moving() ? 'moving' : 'idle';
  }
  const STATE_TEXT = { lost: 'connection lost', held: 'paused' };

  function percent(state) {
    const p = m.prog;
    if (!p.nl || !p.la) return 0;
    if (state === 'finished') return 100;
    return Math.min(99, Math.floor(((p.la - 1) / p.nl) * 100));
  }

  const clock = (s) => {
    s = Math.max(0, Math.round(s));
    const h = Math.floor(s / 3600),
      mi = Math.floor((s % 3600) / 60),
      se = s % 60;
    return (h ? h + ':' + String(mi).padStart(2, '0') : mi) + ':' + String(se).padStart(2, '0');
  };

  // ---- Rendering ----------------------------------------------------------------------------

  let renderQueued = false;
  function scheduleRender() {
    if (!renderQueued) {
      renderQueued = true;
      setTimeout(() => {
        renderQueued = false;
        render();
      }, 80);
    }
  }

  function render() {
    const state = machineState();
    const conn = $('conn');
    conn.dataset.state = m.link;
    conn.textContent =
      m.link === 'up'
        ? m.role === 'watch'
          ? 'connected, watching'
          : 'connected'
        : m.link === 'lost'
          ? 'connection lost'
          : 'connecting…';
    const role = $('role');
    role.hidden = m.role !== 'watch';
    role.textContent = 'watching — another client controls the machine';
    $('machine').textContent = m.machine;
    const st = $('state');
    st.dataset.state = state;
    st.textContent = STATE_TEXT[state] || state;

    // Position.
    const head = m.axes.map((a) => `<th scope="col">${a.l}</th>`).join('');
    if ($('pos-head').innerHTML !== head) {
      $('pos-head').innerHTML = head;
      $('pos-row').innerHTML = m.axes.map((a) => `<td id="pos-${a.l}"></td>`).join('');
    }
    for (const a of m.axes) $('pos-' + a.l).textContent = a.mm.toFixed(3);

    // Progress.
    const p = m.prog;
    const pct = percent(state);
    $('progress').setAttribute('aria-valuenow', String(pct));
    $('progress-fill').style.width = pct + '%';
    $('progress-pct').textContent = pct + ' %';
    $('line').textContent = p.nl
      ? p.la
        ? `line ${p.la} of ${p.nl}`
        : `${p.nl} lines stored, upload incomplete`
      : '';
    $('job-name').textContent = m.selected
      ? 'file ' + m.selected
      : p.nl
        ? 'stored program'
        : 'no program';
    $('elapsed').textContent = clock(p.el);
    const active = ['running', 'paused', 'pausing', 'held'].includes(state);
    let remaining = '–';
    if (state === 'finished') remaining = '0:00';
    else if (active && p.es > 0) remaining = clock(p.es - p.el);
    else if (active && p.la > 1 && p.nl)
      remaining = '≈ ' + clock((p.el * p.nl) / (p.la - 1) - p.el);
    $('remaining').textContent = remaining;
    $('estimated').textContent = p.es > 0 ? clock(p.es) : '–';

    // Controls: a watcher's are all disabled; the rest follow the state.
    const control = m.role === 'control' && m.link === 'up';
    for (const f of document.querySelectorAll('fieldset.ctl')) f.disabled = !control;
    const still = !active && state !== 'homing';
    const paused = state === 'paused' || state === 'held';
    $('btn-start').disabled = !still || m.alarm !== null || !p.nl;
    $('btn-pause').disabled = !(state === 'running');
    $('btn-resume').disabled = !paused;
    $('btn-stop').disabled = !(active || state === 'homing' || state === 'moving');
    $('btn-rewind').disabled = !still || !p.nl;
    $('btn-reset').disabled = false;
    for (const b of document.querySelectorAll('[data-jog], #btn-home'))
      b.disabled = !still || (!!m.alarm && b.id !== 'btn-home');
    $('btn-upload').disabled = active || m.uploading;
    $('upload-to').options[1].disabled = !m.sd;
    $('upload-name').hidden = $('upload-to').value !== 'card';
    for (const b of document.querySelectorAll('#files button'))
      b.disabled = b.dataset.act !== 'none' && (active || m.uploading);
    $('temps-panel').hidden = !Object.keys(m.heaters).length;
    st.title = m.alarm || '';
    if (m.alarm && $('notice').hidden)
      say(`Machine stopped: ${m.alarm}. Reset it, or home it.`, true);
    renderTemps();
  }

  function say(text, bad) {
    const n = $('notice');
    n.hidden = !text;
    n.textContent = text || '';
    n.className = 'notice';
    clearTimeout(say.timer);
    if (text)
      say.timer = setTimeout(
        () => {
          n.hidden = true;
        },
        bad ? 12000 : 5000,
      );
  }

  // ---- Console --------------------------------------------------------------------------

  function logLine(text, cls) {
    const log = $('console-log');
    const atEnd = log.scrollTop + log.clientHeight >= log.scrollHeight - 4;
    const d = document.createElement('div');
    d.textContent = text;
    if (cls) d.className = cls;
    log.appendChild(d);
    while (log.childNodes.length > 400) log.removeChild(log.firstChild);
    if (atEnd) log.scrollTop = log.scrollHeight;
  }

  $('console-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const input = $('console-input');
    const line = input.value.trim();
    if (!line) return;
    if (/[^ -~]/.test(line)) {
      logLine('not sent: printable ASCII only', 'err');
      return;
    }
    if (/^\$/.test(line) || line === '?') {
      logLine(
        'not sent: grbl commands would switch the link to the grbl dialect, ' +
          'which this page does not speak',
        'err',
      );
      return;
    }
    input.value = '';
    if (/^M112\b/i.test(line)) {
      estop();
      return;
    }
    await gcode(line);
  });

  // ---- Job ------------------------------------------------------------------------------

  function action(kw, intent) {
    if (m.role !== 'control') return;
    raw(actionFrame(kw) + '\n');
    logLine('> ' + kw, 'tx');
    if (intent !== undefined) {
      m.intent = intent;
      m.intentAt = now();
    }
    render();
  }
  $('btn-start').onclick = async () => {
    if (m.selected) {
      const r = await gcode('M24');
      if (!r.ok) {
        say(r.error, true);
        return;
      }
      m.intent = 'run';
      m.intentAt = now();
      return;
    }
    action('Start', 'run');
  };
  $('btn-pause').onclick = () => action('Pause', 'pause');
  $('btn-resume').onclick = () => action('Start', 'run');
  $('btn-stop').onclick = () => action('Stop', null);
  $('btn-rewind').onclick = () => action('Rewind', null);
  $('btn-reset').onclick = () => {
    m.alarm = null;
    say('');
    action('Reset', null);
  };
  function estop() {
    if (m.role !== 'control') return;
    // M112 acts as it arrives, ahead of the lines before it; its `ok` comes in turn.
    const e = { line: 'M112', auto: false, done: () => {}, lines: [], error: null };
    gq.flight.push(e);
    gq.bytes += 5;
    raw('M112\n');
    logLine('> M112', 'tx');
  }
  $('btn-estop').onclick = estop;

  // ---- Jog and home ---------------------------------------------------------------------

  for (const b of document.querySelectorAll('[data-jog]')) {
    b.addEventListener('click', async () => {
      const axis = b.dataset.jog[0],
        sign = b.dataset.jog[1] === '-' ? '-' : '';
      const step = (document.querySelector('input[name=step]:checked') || {}).value || '1';
      const feed = +$('jog-feed').value;
      if (!(feed >= 1 && feed <= 100000)) {
        say('Feed: a number of mm/min from 1 to 100000', true);
        return;
      }
      // As printer hosts jog: relative for one move, then absolute again.
      gcode('G91', { auto: true });
      const r = gcode(`G1 ${axis}${sign}${step} F${Math.round(feed)}`);
      gcode('G90', { auto: true });
      const res = await r;
      if (!res.ok) say('Jog refused: ' + res.error, true);
    });
  }
  $('btn-home').onclick = async () => {
    m.homing = true;
    render();
    const r = await gcode('G28');
    m.homing = false;
    if (!r.ok) say('Homing refused: ' + r.error, true);
    render();
  };

  // ---- Files: upload, list, select, run, delete --------------------------------------------

  function uploadMsg(text, cls) {
    const el = $('upload-msg');
    el.textContent = text;
    el.className = 'msg ' + (cls || '');
  }

  $('upload-to').onchange = () => render();
  $('upload-file').onchange = () => {
    const f = $('upload-file').files[0];
    if (f)
      $('upload-name').value = f.name
        .replace(/[^!-~]|[/\\"*:<>?|;]/g, '_')
        .replace(/^\./, '_')
        .slice(0, 63)
        .toUpperCase();
  };

  $('btn-upload').onclick = async () => {
    const f = $('upload-file').files[0];
    if (!f) {
      uploadMsg('Choose a file first.', 'err');
      return;
    }
    if (f.size > 2e6) {
      uploadMsg('The file is over 2 MB: stream it from a host instead.', 'err');
      return;
    }
    const text = await f.text();
    const card = $('upload-to').value === 'card';
    m.uploading = true;
    render();
    try {
      if (card) await uploadCard($('upload-name').value.trim(), text);
      else await uploadProgram(f.name, text);
    } catch (why) {
      uploadMsg(String(why), 'err');
    }
    m.uploading = false;
    m.uploadingFrames = false;
    pump();
    await listFiles();
    render();
  };

  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
  async function drained() {
    while (gq.flight.length || gq.queue.length || pollsOut) await sleep(20);
  }

  // The program store: frames 03, ten at a time, each batch checked with 04 52 as `forja
  // upload` does; a line the controller did not store is sent again from the first missing.
  async function uploadProgram(name, text) {
    const lines = compile(text, true); // nothing is sent unless every line fits
    const total = lines.length;
    if (total > 9999)
      throw `The file has ${total} lines; the program store holds 9999: use the SD card.`;
    uploadMsg(`Uploading ${total} lines…`);
    m.uploadingFrames = true;
    await drained();
    m.uploadErrors = [];
    const bar = $('upload-bar');
    let next = 1,
      stalls = 0;
    while (next <= total) {
      const end = Math.min(next + 9, total);
      let out = '';
      for (let i = next; i <= end; i++) out += loadFrame(i, lines[i - 1].text, total) + '\n';
      const p = await waitFor(request('52', out), 4000);
      const fatal = m.uploadErrors.find((e) => FATAL_UPLOAD.includes(e.code));
      if (fatal) throw 'Upload refused: ' + fatal.text;
      if (!p) throw 'Upload failed: the controller did not answer';
      const before = next;
      if (p.nl + 1 < next) next = 1;
      else next = Math.min(p.nl, total) + 1;
      if (next > before) stalls = 0;
      else if (++stalls >= 5) {
        const e = m.uploadErrors[m.uploadErrors.length - 1];
        throw (
          `Upload stopped at line ${next}: ` + (e ? e.text : 'the controller does not store it')
        );
      }
      bar.value = Math.round(((next - 1) / total) * 100);
      uploadMsg(`Uploading: ${next - 1} of ${total} lines`);
    }
    m.uploadingFrames = false;
    m.selected = null;
    keepText('program', lines.map((l) => l.text).join('\n'));
    setPreview('program', lines);
    uploadMsg(`Stored ${total} lines in the program store: Start runs it.`, 'ok');
  }

  // The SD card: M28 <name>, the lines, M29 (docs/protocol.md §7.7).
  async function uploadCard(name, text) {
    if (
      !/^[!-~]{1,63}$/.test(name) ||
      /[/\\"*:<>?|;]/.test(name.replace(/^\//, '')) ||
      name.startsWith('.')
    ) {
      throw (
        'The card takes names of 1 to 63 printable characters, without spaces, ' +
        'slashes or * : < > ? | ; and not starting with a dot.'
      );
    }
    const lines = compile(text, false);
    const open = await gcode('M28 ' + name);
    if (!open.ok) {
      await gcode('M29');
      throw 'Upload refused: ' + open.error;
    }
    const bar = $('upload-bar');
    let done = 0,
      refused = null;
    const pending = lines.map((l) =>
      gcode(l.text, { auto: true }).then((r) => {
        done++;
        if (!r.ok && !refused) refused = `line ${l.src}: ${r.error}`;
        if (done % 20 === 0 || done === lines.length) {
          bar.value = Math.round((done / lines.length) * 100);
          uploadMsg(`Uploading: ${done} of ${lines.length} lines`);
        }
      }),
    );
    await Promise.all(pending);
    const close = await gcode('M29');
    if (refused) {
      // The card has no way to abandon a file: what M29 finished lacks the refused line.
      await gcode('M30 ' + name);
      throw `Upload refused, ${refused}; the incomplete ${name} was deleted from the card.`;
    }
    if (!close.ok) throw 'The card did not finish the file: ' + close.error;
    keepText('file:' + name.toUpperCase(), lines.map((l) => l.text).join('\n'));
    uploadMsg(`Wrote ${name} (${lines.length} lines) to the card.`, 'ok');
  }

  async function listFiles() {
    if (m.role !== 'control') return;
    const r = await gcode('M20', { auto: true });
    m.files = [];
    m.program = null;
    for (const l of r.lines) {
      let f;
      if ((f = /^program (\d+)\/(\d+) (complete|incomplete)$/.exec(l))) {
        m.program = { stored: +f[1], total: +f[2], complete: f[3] === 'complete' };
      } else if ((f = /^(\S+) (\d+)$/.exec(l))) {
        m.files.push({ name: f[1], size: +f[2] });
      }
    }
    if (
      m.program &&
      m.program.complete &&
      !m.selected &&
      (!m.preview || m.preview.name !== 'program')
    ) {
      const t = cachedText('program');
      if (t && t.split('\n').length === m.program.total) setPreview('program', compile(t, true));
    }
    renderFiles();
  }

  function renderFiles() {
    const rows = [];
    const esc = (s) =>
      s.replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);
    if (m.program) {
      rows.push(
        `<tr class="${m.selected ? '' : 'current'}"><td>program store</td>` +
          `<td>${m.program.stored}/${m.program.total} lines` +
          `${m.program.complete ? '' : ', incomplete'}</td><td>` +
          '<button type="button" data-act="run-program" id="run-program">Run</button></td></tr>',
      );
    }
    for (const f of m.files) {
      const n = esc(f.name);
      rows.push(
        `<tr class="${m.selected === f.name ? 'current' : ''}">` +
          `<td>${n}</td><td>${f.size} B</td><td>` +
          `<button type="button" data-act="select" data-name="${n}">Select</button> ` +
          `<button type="button" data-act="run" data-name="${n}">Run</button> ` +
          `<button type="button" data-act="delete" data-name="${n}" aria-label="Delete ${n}">` +
          'Delete</button></td></tr>',
      );
    }
    if (!rows.length) rows.push('<tr><td colspan="3" class="small">nothing stored</td></tr>');
    $('files').innerHTML = rows.join('');
    render();
  }

  $('files').addEventListener('click', async (ev) => {
    const b = ev.target.closest('button');
    if (!b) return;
    const name = b.dataset.name;
    if (b.dataset.act === 'run-program') {
      if (m.selected) {
        // Nothing selects the stored program again but releasing the card (docs/protocol.md §7.7).
        const rel = await gcode('M22');
        if (!rel.ok) {
          say(rel.error, true);
          return;
        }
        await gcode('M21');
        m.selected = null;
      }
      const t = cachedText('program');
      if (t) setPreview('program', compile(t, true));
      action('Start', 'run');
    } else if (b.dataset.act === 'select' || b.dataset.act === 'run') {
      const r = await gcode('M23 ' + name);
      if (!r.ok || r.lines.some((l) => /^open failed/.test(l))) {
        say('Cannot select ' + name + ': ' + (r.error || 'open failed'), true);
        return;
      }
      m.selected = name;
      const t = cachedText('file:' + name.toUpperCase());
      m.preview = null;
      if (t) setPreview(name, compile(t, false));
      drawPreviewSoon();
      if (b.dataset.act === 'run') {
        const s = await gcode('M24');
        if (!s.ok) say(s.error, true);
        else {
          m.intent = 'run';
          m.intentAt = now();
        }
      }
    } else if (b.dataset.act === 'delete') {
      if (!confirm('Delete ' + name + ' from the card?')) return;
      const r = await gcode('M30 ' + name);
      if (!r.ok) say('Cannot delete ' + name + ': ' + r.error, true);
      if (m.selected === name) m.selected = null;
    }
    await listFiles();
  });
  $('btn-files').onclick = () => listFiles();

  // The controller cannot send a program back: the page keeps the text of what it uploaded.
  function keepText(key, text) {
    try {
      if (text.length < 400000) localStorage.setItem('forja:' + key, text);
    } catch (e) {
      /* full */
    }
  }
  function cachedText(key) {
    try {
      return localStorage.getItem('forja:' + key);
    } catch (e) {
      return null;
    }
  }

  // ---- Toolpath preview -----------------------------------------------------------------------

  // XY segments of each stored line, as the kernel reads G0–G3 (G90/G91, G20/G21, G92, G17
  // arcs by I/J or R); `line` is the line's index in the stored program (frame 52's LA).
  function toolpath(lines) {
    const segs = [];
    let x = 0,
      y = 0,
      mode = 0,
      rel = false,
      relE = false,
      unit = 1,
      ox = 0,
      oy = 0,
      e = 0;
    const printer = m.axes.some((a) => a.l === 'E');
    const start = m.axes.length >= 2 ? m.axes : null;
    if (start) {
      x = start[0].mm;
      y = start[1].mm;
    }
    lines.forEach((ln, k) => {
      const w = {};
      const gs = [];
      for (const word of ln.p.words) {
        if (word.l === 'G') gs.push(+word.v);
        else if (word.l === 'M') {
          if (+word.v === 82) relE = false;
          if (+word.v === 83) relE = true;
        } else w[word.l] = word.v === '' ? null : +word.v;
      }
      let motion = null;
      for (const g of gs) {
        // G90/G91 set the extruder too; M82/M83 after them set it alone (Marlin's rule).
        if (g === 90) rel = relE = false;
        else if (g === 91) rel = relE = true;
        else if (g === 20) unit = 25.4;
        else if (g === 21) unit = 1;
        else if (g >= 0 && g <= 3 && Number.isInteger(g)) {
          mode = g;
          motion = g;
        } else if (g === 28) {
          x = 0;
          y = 0;
          ox = 0;
          oy = 0;
        } else if (g === 92) {
          if (w.X != null) ox = x - w.X * unit;
          if (w.Y != null) oy = y - w.Y * unit;
          return;
        }
      }
      if (gs.includes(28) || gs.includes(53) || gs.includes(4) || gs.includes(10)) return;
      if (w.X === undefined && w.Y === undefined && motion === null) return;
      if (w.X === undefined && w.Y === undefined) return;
      const nx = w.X == null ? x : rel ? x + w.X * unit : w.X * unit + ox;
      const ny = w.Y == null ? y : rel ? y + w.Y * unit : w.Y * unit + oy;
      const extrude = w.E != null && (relE ? w.E > 0 : w.E > e);
      if (w.E != null) e = relE ? e + w.E : w.E;
      // 0 a rapid, 1 a cut or an extrusion, 2 a printer's travel
      const kind = mode === 0 ? 0 : printer && !extrude ? 2 : 1;
      if (mode === 2 || mode === 3) {
        let cx, cy;
        if (w.R != null) {
          const r = w.R * unit,
            dx = nx - x,
            dy = ny - y,
            d = Math.hypot(dx, dy);
          const hh =
            Math.sqrt(Math.max(0, r * r - (d * d) / 4)) * ((mode === 2) === r > 0 ? -1 : 1);
          cx = x + dx / 2 - (hh * dy) / (d || 1);
          cy = y + dy / 2 + (hh * dx) / (d || 1);
        } else {
          cx = x + (w.I || 0) * unit;
          cy = y + (w.J || 0) * unit;
        }
        let a0 = Math.atan2(y - cy, x - cx),
          a1 = Math.atan2(ny - cy, nx - cx);
        if (mode === 2 && a1 >= a0) a1 -= 2 * Math.PI;
        if (mode === 3 && a1 <= a0) a1 += 2 * Math.PI;
        const r = Math.hypot(x - cx, y - cy);
        const n = Math.max(2, Math.ceil(Math.abs(a1 - a0) / 0.1));
        let px = x,
          py = y;
        for (let i = 1; i <= n; i++) {
          const a = a0 + ((a1 - a0) * i) / n;
          const qx = i === n ? nx : cx + r * Math.cos(a),
            qy = i === n ? ny : cy + r * Math.sin(a);
          segs.push([px, py, qx, qy, kind, k + 1]);
          px = qx;
          py = qy;
        }
      } else if (nx !== x || ny !== y) {
        segs.push([x, y, nx, ny, kind, k + 1]);
      }
      x = nx;
      y = ny;
    });
    return segs;
  }

  function setPreview(name, lines) {
    const segs = toolpath(lines);
    let b = [Infinity, Infinity, -Infinity, -Infinity];
    for (const s of segs) {
      b = [
        Math.min(b[0], s[0], s[2]),
        Math.min(b[1], s[1], s[3]),
        Math.max(b[2], s[0], s[2]),
        Math.max(b[3], s[1], s[3]),
      ];
    }
    m.preview = { name, segs, bounds: segs.length ? b : [0, 0, 1, 1], lines: lines.length };
    drawPreviewSoon();
  }

  let previewQueued = false;
  function drawPreviewSoon() {
    if (!previewQueued) {
      previewQueued = true;
      requestAnimationFrame(() => {
        previewQueued = false;
        drawPreview();
      });
    }
  }
  function css(name) {
    return getComputedStyle(document.documentElement).getPropertyValue(name).trim();
  }
  function fitCanvas(c) {
    const r = c.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(100, Math.round(r.width * dpr)),
      h = Math.max(60, Math.round(r.height * dpr));
    if (c.width !== w || c.height !== h) {
      c.width = w;
      c.height = h;
    }
    return { ctx: c.getContext('2d'), w, h, dpr };
  }

  function drawPreview() {
    const c = $('preview');
    const { ctx, w, h, dpr } = fitCanvas(c);
    ctx.clearRect(0, 0, w, h);
    const pv = m.preview;
    ctx.font = `${12 * dpr}px system-ui, sans-serif`;
    ctx.fillStyle = css('--muted');
    if (!pv || !pv.segs.length) {
      ctx.fillText(
        pv ? 'the program has no XY moves' : 'no toolpath: upload a program from this page',
        10 * dpr,
        20 * dpr,
      );
      return;
    }
    const [x0, y0, x1, y1] = pv.bounds;
    const pad = 14 * dpr,
      top = 28 * dpr; // the caption has the band above
    const sc = Math.min(
      (w - 2 * pad) / Math.max(x1 - x0, 1e-3),
      (h - top - pad) / Math.max(y1 - y0, 1e-3),
    );
    const ox = (w - (x1 - x0) * sc) / 2,
      oy = top + (h - top - pad - (y1 - y0) * sc) / 2;
    const X = (x) => ox + (x - x0) * sc,
      Y = (y) => oy + (y1 - y) * sc;
    const finished = machineState() === 'finished';
    const done = finished ? Infinity : m.prog.la || 0;
    const current = !m.selected === (pv.name === 'program');
    const stroke = (executed) => {
      for (const kind of [0, 2, 1]) {
        ctx.beginPath();
        for (const s of pv.segs) {
          if (s[4] !== kind || (executed && (!current || s[5] >= done))) continue;
          ctx.moveTo(X(s[0]), Y(s[1]));
          ctx.lineTo(X(s[2]), Y(s[3]));
        }
        ctx.setLineDash(kind === 1 ? [] : [4 * dpr, 4 * dpr]);
        ctx.lineWidth = (kind === 1 ? (executed ? 2.5 : 1.5) : 1) * dpr;
        ctx.strokeStyle = executed ? css('--done') : css('--path');
        ctx.globalAlpha = kind === 1 ? 1 : 0.6;
        ctx.stroke();
      }
      ctx.setLineDash([]);
      ctx.globalAlpha = 1;
    };
    stroke(false);
    stroke(true);
    // The line under way: its segments up to the one nearest the tool, that one up to it.
    const tool = m.axes.length >= 2 && [m.axes[0].mm, m.axes[1].mm];
    const under = current && !finished && tool && pv.segs.filter((s) => s[5] === done);
    if (under && under.length) {
      let best = 0,
        bestD = Infinity,
        bestF = 0;
      under.forEach((s, i) => {
        const dx = s[2] - s[0],
          dy = s[3] - s[1];
        const f = Math.max(
          0,
          Math.min(1, ((tool[0] - s[0]) * dx + (tool[1] - s[1]) * dy) / (dx * dx + dy * dy || 1)),
        );
        const d = Math.hypot(s[0] + f * dx - tool[0], s[1] + f * dy - tool[1]);
        if (d < bestD) {
          best = i;
          bestD = d;
          bestF = f;
        }
      });
      if (bestD < 1) {
        ctx.beginPath();
        under.slice(0, best + 1).forEach((s, i) => {
          const f = i === best ? bestF : 1;
          ctx.moveTo(X(s[0]), Y(s[1]));
          ctx.lineTo(X(s[0] + f * (s[2] - s[0])), Y(s[1] + f * (s[3] - s[1])));
        });
        ctx.lineWidth = (under[0][4] === 1 ? 2.5 : 1) * dpr;
        ctx.strokeStyle = css('--done');
        ctx.stroke();
      }
    }
    if (m.axes.length >= 2) {
      ctx.fillStyle = css('--tool');
      ctx.beginPath();
      ctx.arc(X(m.axes[0].mm), Y(m.axes[1].mm), 4.5 * dpr, 0, 2 * Math.PI);
      ctx.fill();
    }
    ctx.fillStyle = css('--muted');
    ctx.fillText(
      `${pv.name === 'program' ? 'program store' : pv.name}: ` +
        `X ${x0.toFixed(1)}…${x1.toFixed(1)}, Y ${y0.toFixed(1)}…${y1.toFixed(1)} mm`,
      8 * dpr,
      16 * dpr,
    );
  }
  window.addEventListener('resize', () => {
    drawPreviewSoon();
    renderTemps();
  });

  // ---- Temperatures -------------------------------------------------------------------------

  const HEATER_NAME = { T: 'Hot end', T0: 'Hot end', T1: 'Hot end 2', B: 'Bed', C: 'Chamber' };
  const HEATER_SET = { T: 'M104 S', T0: 'M104 T0 S', T1: 'M104 T1 S', B: 'M140 S', C: 'M141 S' };
  const COLORS = ['#dc2626', '#2563eb', '#16a34a', '#9333ea'];

  function temperatures(line) {
    const re = /(?:^|\s)(T\d?|B|C):(-?[\d.]+) *\/(-?[\d.]+)/g;
    let r,
      any = false;
    while ((r = re.exec(line))) {
      m.heaters[r[1]] = { now: +r[2], target: +r[3] };
      any = true;
    }
    if (!any) return;
    const t = now();
    const last = m.tempHist[m.tempHist.length - 1];
    if (!last || t - last.t > 900) {
      const sample = { t };
      for (const k in m.heaters) sample[k] = m.heaters[k].now;
      m.tempHist.push(sample);
      if (m.tempHist.length > 300) m.tempHist.shift();
    }
  }

  function renderTemps() {
    const keys = Object.keys(m.heaters);
    if (!keys.length) return;
    const body = $('temps');
    if (body.dataset.keys !== keys.join()) {
      body.dataset.keys = keys.join();
      body.innerHTML = keys
        .map(
          (k, i) =>
            `<tr><th scope="row"><span style="color:${COLORS[i % 4]}">■</span> ` +
            `${HEATER_NAME[k] || k}</th><td id="temp-${k}"></td><td id="target-${k}"></td>` +
            `<td><form data-heater="${k}"><fieldset class="ctl">` +
            `<label class="sr" for="set-${k}">Target of ${HEATER_NAME[k] || k}, °C</label>` +
            `<input id="set-${k}" type="number" min="0" max="400" step="1" inputmode="numeric">` +
            ' <button type="submit">Set</button></fieldset></form></td></tr>',
        )
        .join('');
      for (const f of body.querySelectorAll('form')) {
        f.addEventListener('submit', async (ev) => {
          ev.preventDefault();
          const k = f.dataset.heater;
          const v = f.querySelector('input').value.trim();
          if (!/^\d{1,3}(\.\d)?$/.test(v)) {
            say('Target: a temperature in °C, 0 to turn the heater off', true);
            return;
          }
          const r = await gcode(HEATER_SET[k] + v);
          if (!r.ok) say('Refused: ' + r.error, true);
        });
      }
      render();
    }
    for (const k of keys) {
      $('temp-' + k).textContent = m.heaters[k].now.toFixed(1) + ' °C';
      $('target-' + k).textContent = m.heaters[k].target
        ? m.heaters[k].target.toFixed(0) + ' °C'
        : 'off';
    }
    const c = $('temp-chart');
    if (c.offsetParent === null) return;
    const { ctx, w, h, dpr } = fitCanvas(c);
    ctx.clearRect(0, 0, w, h);
    const hist = m.tempHist;
    let top = 50;
    for (const s of hist) for (const k of keys) top = Math.max(top, s[k] || 0);
    for (const k of keys) top = Math.max(top, m.heaters[k].target);
    top = Math.ceil((top + 10) / 50) * 50;
    const pad = 28 * dpr;
    const t1 = now();
    const span = Math.min(300e3, Math.max(60e3, hist.length ? t1 - hist[0].t : 0));
    const X = (t) => pad + ((w - pad - 6 * dpr) * (t - (t1 - span))) / span;
    const Y = (v) => h - 6 * dpr - ((h - 12 * dpr) * v) / top;
    ctx.font = `${10 * dpr}px system-ui, sans-serif`;
    ctx.fillStyle = css('--muted');
    ctx.strokeStyle = css('--line');
    ctx.lineWidth = dpr;
    const tick = [10, 20, 25, 50, 100, 200].find((d) => top / d <= 5) || 250;
    for (let v = 0; v <= top; v += tick) {
      ctx.beginPath();
      ctx.moveTo(pad, Y(v));
      ctx.lineTo(w, Y(v));
      ctx.stroke();
      ctx.fillText(String(Math.round(v)), 2 * dpr, Y(v) + 3 * dpr);
    }
    keys.forEach((k, i) => {
      ctx.strokeStyle = COLORS[i % 4];
      ctx.lineWidth = 2 * dpr;
      ctx.beginPath();
      let first = true;
      for (const s of hist) {
        if (s[k] === undefined || s.t < t1 - span) continue;
        if (first) ctx.moveTo(X(s.t), Y(s[k]));
        else ctx.lineTo(X(s.t), Y(s[k]));
        first = false;
      }
      ctx.stroke();
      if (m.heaters[k].target) {
        ctx.setLineDash([3 * dpr, 3 * dpr]);
        ctx.lineWidth = dpr;
        ctx.beginPath();
        ctx.moveTo(pad, Y(m.heaters[k].target));
        ctx.lineTo(w, Y(m.heaters[k].target));
        ctx.stroke();
        ctx.setLineDash([]);
      }
    });
  }

  // ---- Settings (frames 00, docs/protocol.md §7.3) ------------------------------------------

  const GLOBAL_SETTINGS = [
    'jog_feed',
    'default_feed',
    'junction_deviation',
    'arc_tolerance',
    'hard_limits',
    'soft_limits',
    'keep_alive_ms',
    'power_loss_recovery',
    'print_accel',
    'retract_accel',
    'travel_accel',
    'min_print_feed',
    'min_travel_feed',
    'status_mask',
    'report_inches',
    'laser_mode',
    'startup_line0',
    'startup_line1',
  ];
  const AXIS_SETTINGS = [
    'steps_per_mm',
    'max_rate',
    'accel',
    'min',
    'max',
    'homing_seek',
    'homing_locate',
    'homing_pull_off',
  ];

  function settingKeys() {
    const keys = [];
    for (const a of m.axes) for (const s of AXIS_SETTINGS) keys.push(a.l.toLowerCase() + '.' + s);
    return keys.concat(GLOBAL_SETTINGS);
  }

  // Read or set one setting: resolves with { key, value } or { error }.
  function setting(key, value) {
    return new Promise((done) => {
      if (m.role !== 'control') {
        done({ error: 'this page does not control the machine' });
        return;
      }
      const payload = value === undefined ? key : key + '=' + value;
      if (payload.length > PAYLOAD || /[^ -~]|\*/.test(payload)) {
        done({
          error: `a setting's key and value fit ${PAYLOAD} printable characters, without "*"`,
        });
        return;
      }
      want50.push({ key, done, write: value !== undefined });
      raw(frame('00', payload) + '\n');
      setTimeout(() => {
        const k = want50.findIndex((w) => w.done === done);
        if (k >= 0) {
          want50.splice(k, 1);
          done({ error: 'no answer' });
        }
      }, 3000);
    });
  }

  function showSetting(key, value) {
    const k = key.toLowerCase();
    if (k === 'link.ssid') {
      $('wifi-now').textContent = value
        ? `The board joins "${value}" at its next start.`
        : 'No network set: a board that has an access point offers its own at its next start.';
      if (document.activeElement !== $('wifi-ssid')) $('wifi-ssid').value = value;
      return;
    }
    if (k.startsWith('link.')) return;
    const input = settingInput(k);
    if (document.activeElement !== input) input.value = value;
  }

  // The row of setting `k`, made when its first answer comes (a watcher's too).
  function settingInput(k) {
    const id = 'setting-' + k;
    if ($(id)) return $(id);
    const tr = document.createElement('tr');
    const label = document.createElement('label');
    label.htmlFor = id;
    label.textContent = k;
    const input = document.createElement('input');
    input.id = id;
    input.spellcheck = false;
    input.maxLength = PAYLOAD - k.length - 1;
    const save = document.createElement('button');
    save.type = 'button';
    save.textContent = 'Save';
    save.dataset.key = k;
    for (const el of [label, input, save])
      tr.appendChild(document.createElement('td')).appendChild(el);
    $('settings').appendChild(tr);
    return input;
  }

  $('btn-settings').onclick = () => readSettings();
  async function readSettings() {
    if (!m.axes.length) await waitFor(request('51'), 3000);
    const keys = settingKeys();
    $('settings').textContent = '';
    $('settings-msg').textContent = 'Reading…';
    $('settings-msg').className = 'msg';
    let shown = 0;
    for (let i = 0; i < keys.length; i += 8) {
      const answers = await Promise.all(keys.slice(i, i + 8).map((k) => setting(k)));
      shown += answers.filter((a) => !a.error).length;
    }
    await setting('link.ssid');
    $('settings-msg').textContent = `${shown} settings.`;
  }

  $('settings').addEventListener('click', async (ev) => {
    const b = ev.target.closest('button');
    if (!b) return;
    const key = b.dataset.key;
    const value = settingInput(key).value.trim();
    const r = await setting(key, value);
    const msg = $('settings-msg');
    msg.textContent = r.error ? `${key} not changed: ${r.error}` : `${key} = ${r.value} stored.`;
    msg.className = 'msg ' + (r.error ? 'err' : 'ok');
  });

  // ---- WiFi: link.ssid and link.password (app/src/wifi.rs) ------------------------------------

  function wifiMsg(text, bad) {
    $('wifi-msg').textContent = text;
    $('wifi-msg').className = 'msg ' + (bad ? 'err' : 'ok');
  }
  $('wifi-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const ssid = $('wifi-ssid').value,
      pass = $('wifi-pass').value;
    if (!/^[ -~]{1,32}$/.test(ssid) || ssid.includes('*')) {
      wifiMsg('The network name: 1 to 32 printable characters, without "*".', true);
      return;
    }
    if (pass && (!/^[ -~]{8,35}$/.test(pass) || pass.includes('*'))) {
      wifiMsg(
        'The password: empty for an open network, else 8 to 35 printable characters without "*".',
        true,
      );
      return;
    }
    // The password first: the board joins as soon as the name makes the pair valid.
    const p = await setting('link.password', pass);
    if (p.error) {
      wifiMsg('Not changed: ' + p.error, true);
      return;
    }
    const s = await setting('link.ssid', ssid);
    if (s.error) {
      wifiMsg('Not changed: ' + s.error, true);
      return;
    }
    $('wifi-pass').value = '';
    wifiMsg(`Stored: the board joins "${s.value}" at its next start.`);
  });
  $('btn-wifi-forget').onclick = async () => {
    const s = await setting('link.ssid', '');
    if (s.error) wifiMsg('Not changed: ' + s.error, true);
    else wifiMsg('Stored: at its next start the board offers its own access point, if it has one.');
  };

  connect();
  render();
})();
