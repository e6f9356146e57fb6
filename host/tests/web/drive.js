#!/usr/bin/env node
// Drive the operator's web page (web/page/) in a real headless Chromium against the simulator,
// as a person at the machine would: through the page's own buttons, fields and file picker.
//
// Usage: node drive.js --modules DIR --chromium BIN --url URL --sim-pid PID --program FILE
//                      --bad FILE --out DIR --workdir DIR [--seconds N]
//
// DIR is the node_modules that holds puppeteer-core (it drives Chromium over the DevTools
// protocol and downloads no browser); BIN the system's Chromium, run headless (new mode) with
// --no-sandbox --disable-gpu. URL is the page as the simulator serves it; FILE the program to
// upload (a printer's: the page shows temperatures), --bad one the page must refuse; PID the
// simulator's process, which the `lost` step stops for a while (SIGSTOP, then SIGCONT).
//
// The steps, in this order:
//
//   load     page A loads (no request fails, no script error), connects, and controls the
//            machine: no watch notice, the state idle, the position shown
//   watch    page B, a second client, is told it watches: the page says "watching — another
//            client controls the machine" and its controls are disabled; it shows the same
//            position as page A
//   upload   A uploads FILE into the program store through the file picker: the page reports
//            its lines stored, the file list shows the program complete, the toolpath is drawn
//   refuse   A picks the bad file: the page names the line and sends nothing (the list still
//            shows FILE's program); a line the controller refuses (G1 X500: longer than the
//            axis) typed in the console shows the controller's refusal there
//   heat     A sets the hot end's target to 200 °C: the page shows the target and the
//            temperature rising
//   start    (screenshot OUT/idle.png) A starts the job: its state shows running and the
//            position moves; B shows it running too
//   pause    (screenshot OUT/job.png, once three fifths of the job are done) A pauses: the state
//            shows paused and the position stays put for a second
//   resume   A resumes: running again, the position moves
//   finish   the progress reaches 100 %, the state shows finished with no time remaining, on
//            A and on B
//   jog      A jogs X by +10 mm (step 10): the page shows X 10 mm further, at rest; M114
//            typed in the console answers the position the page shows, axis by axis
//   lost     the simulator is stopped (SIGSTOP): within 5 s page A's keep-alive finds its
//            polls unanswered and shows "connection lost"; continued (SIGCONT), it shows
//            "connected" again
//   handover page A closes: page B is given control (the server's `// control:` line), its
//            watch notice goes and its controls are enabled
//
// Prints `web: <step> ok …` per step, or `FAILED: <step>: <why>` with the state of both pages
// and their console logs, and exits 1 at the first failure. Chromium is closed whatever
// happens (and the test kills this process group at its time limit).
'use strict';

const fs = require('fs');
const path = require('path');

function options(argv) {
  const o = { seconds: 50 };
  for (let i = 2; i < argv.length; i += 2) o[argv[i].replace(/^--/, '')] = argv[i + 1];
  for (const k of ['modules', 'chromium', 'url', 'sim-pid', 'program', 'bad', 'out', 'workdir']) {
    if (!o[k]) throw new Error(`--${k} is required`);
  }
  return o;
}

const opt = options(process.argv);
const puppeteer = require(path.resolve(opt.modules, 'puppeteer-core'));
const WATCHING = 'watching — another client controls the machine';
// Positions agree when closer than this, mm: the page and M114 both show three decimals.
const TOLERANCE_MM = 0.0015;

class Failed extends Error {}
let step = 'launch';
let stopped = null; // the simulator's pid while it is stopped
const started = Date.now();
const say = (text) => console.log(`web: ${text}`);
const elapsed = () => ((Date.now() - started) / 1000).toFixed(1) + ' s';

// Wait until `test` (async) returns something truthy; `what` names it in the failure.
async function until(test, ms, what) {
  const end = Date.now() + ms;
  let last;
  for (;;) {
    last = await test();
    if (last) return last;
    if (Date.now() > end) throw new Failed(`${what}: not within ${ms / 1000} s`);
    await new Promise((r) => setTimeout(r, 100));
  }
}

// What a page shows: state, connection, role, position, progress, times, the job's line.
function shown(page) {
  return page.evaluate(() => {
    const t = (id) => (document.getElementById(id) || {}).textContent || '';
    const pos = {};
    for (const td of document.querySelectorAll('#pos-row td'))
      pos[td.id.slice(4)] = parseFloat(td.textContent);
    return {
      state: t('state'),
      conn: t('conn'),
      role: document.getElementById('role').hidden ? '' : t('role'),
      pos,
      pct: +document.getElementById('progress').getAttribute('aria-valuenow'),
      elapsed: t('elapsed'),
      remaining: t('remaining'),
      line: t('line'),
      notice: t('notice'),
      upload: t('upload-msg'),
      files: t('files'),
    };
  });
}
const describe = (s) =>
  `state ${s.state}, ${s.conn}${s.role ? ', ' + s.role : ''}, position ${JSON.stringify(s.pos)}, ` +
  `${s.pct} % (${s.line}), elapsed ${s.elapsed}, remaining ${s.remaining}`;
const consoleLog = (page) =>
  page.evaluate(() => [...document.querySelectorAll('#console-log div')].map((d) => d.textContent));
const samePos = (a, b) =>
  Object.keys(a).length > 0 && Object.keys(a).every((k) => Math.abs(a[k] - b[k]) < TOLERANCE_MM);

async function main(browser) {
  const problems = [];
  const open = async (name) => {
    const page = await browser.newPage();
    await page.setViewport({ width: 1280, height: 960 });
    page.on('pageerror', (e) => problems.push(`${name}: script error: ${e.message}`));
    page.on('requestfailed', (r) =>
      problems.push(`${name}: ${r.url()} failed: ${r.failure().errorText}`),
    );
    page.on('response', (r) => {
      if (r.status() >= 400) problems.push(`${name}: ${r.url()} answered ${r.status()}`);
    });
    await page.goto(opt.url, { waitUntil: 'load', timeout: 10000 });
    return page;
  };
  const noProblems = () => {
    if (problems.length) throw new Failed(problems.join('; '));
  };

  step = 'load';
  const a = await open('page A');
  await until(
    async () => {
      const s = await shown(a);
      return s.conn === 'connected' && s.state === 'idle' && s.pos.X !== undefined && s;
    },
    8000,
    'page A connected, idle, showing the position',
  );
  noProblems();
  const first = await shown(a);
  if (first.role) throw new Failed(`page A, the first client, says "${first.role}"`);
  say(`load ok: ${describe(first)} (${elapsed()})`);

  step = 'watch';
  const b = await open('page B');
  await until(async () => (await shown(b)).role === WATCHING, 5000, `page B saying "${WATCHING}"`);
  const disabled = await b.evaluate(() =>
    [
      'btn-start',
      'btn-pause',
      'btn-stop',
      'jog-xp',
      'btn-home',
      'btn-upload',
      'console-input',
      'btn-settings',
      'wifi-ssid',
      'btn-estop',
    ].filter((id) => !document.getElementById(id).matches(':disabled')),
  );
  if (disabled.length)
    throw new Failed(`page B, a watcher, has controls enabled: ${disabled.join(', ')}`);
  await until(
    async () => samePos((await shown(b)).pos, first.pos),
    5000,
    'page B showing the position page A shows',
  );
  if ((await shown(a)).role) throw new Failed('page A says it watches once page B came');
  say(`watch ok: page B says "${WATCHING}", its controls are disabled (${elapsed()})`);

  step = 'upload';
  await a.bringToFront();
  const lines = fs
    .readFileSync(opt.program, 'utf8')
    .split('\n')
    .filter((l) => l.replace(/;.*/, '').trim()).length;
  const pick = async (file) => {
    const input = await a.$('#upload-file');
    await input.uploadFile(file);
    await a.select('#upload-to', 'program');
    await a.click('#btn-upload');
  };
  await pick(opt.program);
  const stored = `Stored ${lines} lines`;
  await until(
    async () => {
      const s = await shown(a);
      if (/refused|failed|stopped|line \d+:/i.test(s.upload))
        throw new Failed(`the page says: ${s.upload}`);
      return s.upload.startsWith(stored) && s.files.includes(`${lines}/${lines} lines`) && s;
    },
    10000,
    `"${stored}" and the program in the file list`,
  );
  const drawn = await a.evaluate(() => {
    const c = document.getElementById('preview');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 3; i < d.length; i += 4) if (d[i]) n++;
    return n;
  });
  if (drawn < 500)
    throw new Failed(`the toolpath preview is (nearly) blank: ${drawn} pixels drawn`);
  say(`upload ok: ${lines} lines stored, toolpath drawn (${drawn} pixels) (${elapsed()})`);

  step = 'refuse';
  await pick(opt.bad);
  await until(
    async () => /line 4: .*39/.test((await shown(a)).upload),
    5000,
    'the page refusing the bad file, naming its line 4',
  );
  const refusal = (await shown(a)).upload;
  await a.click('#btn-files');
  await new Promise((r) => setTimeout(r, 500));
  if (!(await shown(a)).files.includes(`${lines}/${lines} lines`)) {
    throw new Failed(`after the refused upload the file list shows ${(await shown(a)).files}`);
  }
  const before = (await consoleLog(a)).length;
  await a.type('#console-input', 'G1 X500');
  await a.keyboard.press('Enter');
  const echo = await until(
    async () => (await consoleLog(a)).slice(before).find((l) => /^echo:E\d+ /.test(l)),
    5000,
    "the controller's refusal of G1 X500 in the console",
  );
  say(`refuse ok: "${refusal}"; the program is unchanged; G1 X500: "${echo}" (${elapsed()})`);

  step = 'heat';
  await until(() => a.$('#set-T'), 5000, 'the hot end in the temperatures panel');
  await a.type('#set-T', '200');
  await a.evaluate(() => document.getElementById('set-T').form.requestSubmit());
  const heating = await until(
    async () => {
      const t = await a.evaluate(() => [
        document.getElementById('target-T').textContent,
        parseFloat(document.getElementById('temp-T').textContent),
      ]);
      return t[0] === '200 °C' && t[1] > 40 && t;
    },
    8000,
    "the hot end's target 200 °C and its temperature rising past 40 °C",
  );
  say(`heat ok: hot end ${heating[1]} °C, target ${heating[0]} (${elapsed()})`);

  step = 'start';
  fs.mkdirSync(opt.out, { recursive: true });
  await a.screenshot({ path: path.join(opt.out, 'idle.png'), fullPage: true });
  await a.click('#btn-start');
  const startPos = (await shown(a)).pos;
  await until(
    async () => {
      const s = await shown(a);
      return s.state === 'running' && !samePos(s.pos, startPos) && s;
    },
    5000,
    'page A showing the job running and the position moving',
  );
  await until(
    async () => (await shown(b)).state === 'running',
    5000,
    'page B showing the job running',
  );
  say(`start ok: ${describe(await shown(a))} (${elapsed()})`);

  step = 'pause';
  await until(async () => (await shown(a)).pct >= 60, 15000, 'three fifths of the job done');
  await a.screenshot({ path: path.join(opt.out, 'job.png'), fullPage: true });
  await a.click('#btn-pause');
  const paused = await until(
    async () => {
      const s = await shown(a);
      return s.state === 'paused' && s;
    },
    4000,
    'page A showing the job paused',
  );
  await new Promise((r) => setTimeout(r, 1000));
  const still = await shown(a);
  if (!samePos(still.pos, paused.pos) || still.state !== 'paused') {
    throw new Failed(
      `paused, the position moved in a second: ${describe(paused)}, then ${describe(still)}`,
    );
  }
  if (still.pct >= 100)
    throw new Failed(`the job ended before it could be paused: ${describe(still)}`);
  say(`pause ok: ${describe(still)} (${elapsed()})`);

  step = 'resume';
  await a.click('#btn-resume');
  await until(
    async () => {
      const s = await shown(a);
      return s.state === 'running' && !samePos(s.pos, still.pos) && s;
    },
    4000,
    'page A showing the job running again and the position moving',
  );
  say(`resume ok (${elapsed()})`);

  step = 'finish';
  const end = await until(
    async () => {
      const s = await shown(a);
      return s.pct === 100 && s.state === 'finished' && s;
    },
    20000,
    'page A showing the progress at 100 % and the job finished',
  );
  if (end.remaining !== '0:00')
    throw new Failed(`finished, the page shows ${end.remaining} remaining`);
  await until(
    async () => {
      const s = await shown(b);
      return s.pct === 100 && s.state === 'finished';
    },
    5000,
    'page B showing the progress at 100 % and the job finished',
  );
  say(`finish ok: ${describe(end)}; page B shows 100 % too (${elapsed()})`);

  step = 'jog';
  await a.click('#step-10');
  await a.click('#jog-xp');
  const jogged = await until(
    async () => {
      const s = await shown(a);
      return (
        Math.abs(s.pos.X - (end.pos.X + 10)) < TOLERANCE_MM &&
        ['idle', 'finished'].includes(s.state) &&
        s
      );
    },
    8000,
    `page A showing X at ${end.pos.X + 10} and the machine at rest`,
  );
  const mark = (await consoleLog(a)).length;
  await a.type('#console-input', 'M114');
  await a.keyboard.press('Enter');
  const report = await until(
    async () => (await consoleLog(a)).slice(mark).find((l) => /^X:-?\d/.test(l)),
    5000,
    'the M114 report in the console',
  );
  const m114 = {};
  for (const [, axis, mm] of report.matchAll(/\b([XYZE]):(-?\d+\.\d+)/g))
    if (!(axis in m114)) m114[axis] = +mm;
  const now = (await shown(a)).pos;
  const differ = Object.keys(now).filter(
    (k) => !(k in m114) || Math.abs(m114[k] - now[k]) >= TOLERANCE_MM,
  );
  if (differ.length) {
    throw new Failed(
      `the page shows ${JSON.stringify(now)}, M114 answers "${report}" ` +
        `(${differ.join(', ')} differ)`,
    );
  }
  say(
    `jog ok: X ${end.pos.X} -> ${jogged.pos.X}; M114 "${report}" agrees with the page ` +
      `(${elapsed()})`,
  );

  step = 'lost';
  const pid = +opt['sim-pid'];
  process.kill(pid, 'SIGSTOP');
  stopped = pid;
  const lost = Date.now();
  await until(
    async () => {
      const s = await shown(a);
      return s.conn === 'connection lost' && s.state === 'connection lost';
    },
    5000,
    'page A showing "connection lost" while the simulator is stopped',
  );
  const noticed = ((Date.now() - lost) / 1000).toFixed(1);
  process.kill(pid, 'SIGCONT');
  stopped = null;
  await until(async () => (await shown(a)).conn === 'connected', 5000, 'page A connected again');
  say(
    `lost ok: "connection lost" ${noticed} s after the simulator stopped, ` +
      `"connected" once it went on (${elapsed()})`,
  );

  step = 'handover';
  await a.close();
  await b.bringToFront();
  await until(
    async () => {
      const s = await shown(b);
      const enabled = await b.evaluate(
        () =>
          !document.getElementById('jog-xp').matches(':disabled') &&
          !document.getElementById('console-input').matches(':disabled'),
      );
      return s.conn === 'connected' && !s.role && enabled;
    },
    5000,
    'page B in control, its watch notice gone and its controls enabled',
  );
  noProblems();
  say(`handover ok: page B controls the machine once page A left (${elapsed()})`);
  return [b];
}

(async () => {
  let browser;
  let pages = [];
  const deadline = setTimeout(() => {
    if (stopped) process.kill(stopped, 'SIGCONT');
    console.log(`FAILED: ${step}: the time limit (${opt.seconds} s) passed`);
    process.exit(1);
  }, opt.seconds * 1000);
  let code = 0;
  try {
    browser = await puppeteer.launch({
      executablePath: opt.chromium,
      headless: true, // puppeteer passes --headless=new: Chromium's new headless mode
      // Both pages run at once: neither is slowed down as a background tab would be. A
      // container's small /dev/shm is not used.
      args: [
        '--no-sandbox',
        '--disable-gpu',
        '--disable-dev-shm-usage',
        '--no-first-run',
        '--no-default-browser-check',
        '--disable-background-timer-throttling',
        '--disable-renderer-backgrounding',
        '--disable-backgrounding-occluded-windows',
      ],
      userDataDir: path.join(opt.workdir, 'chromium-profile'),
      timeout: 20000,
    });
    pages = await main(browser);
    say(`all steps ok (${elapsed()})`);
  } catch (e) {
    code = 1;
    console.log(`FAILED: ${step}: ${e instanceof Failed ? e.message : e.stack || e}`);
    if (browser) {
      for (const [i, page] of (await browser.pages()).entries()) {
        try {
          console.log(`  page ${i}: ${describe(await shown(page))}`);
          const log = await consoleLog(page);
          console.log(`  page ${i} console, last lines:\n    ${log.slice(-25).join('\n    ')}`);
          await page.screenshot({
            path: path.join(opt.workdir, `failed-${i}.png`),
            fullPage: true,
          });
        } catch (_) {
          /* the page is gone */
        }
      }
    }
  } finally {
    clearTimeout(deadline);
    if (stopped) process.kill(stopped, 'SIGCONT');
    if (browser) await browser.close().catch(() => {});
  }
  process.exit(code || (pages.length ? 0 : 1));
})();
