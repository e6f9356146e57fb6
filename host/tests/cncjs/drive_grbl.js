#!/usr/bin/env node
// Drive a router with CNCjs's own server in its Grbl mode, as its web interface does.
//
// Usage: node drive_grbl.js --cncjs DIR --pty PTY --program FILE --workdir DIR [--seconds N]
//                           [--steps LIST]
//
// The server, its configuration, the socket.io connection, the waits and the failure report
// are drive.js's (see there). The serial traffic is read from CNCjs's log lines
// `controller:Grbl < line` and `> line`: every line received, and what its sender, its feeder
// and its commands write (`!`, `~`, 0x18 and the override bytes too). CNCjs's own polls are not
// there: it writes its `?` status queries and its `$G` parser-state queries to the port
// unlogged (their answers are logged). Positions and machine states are read from CNCjs's
// `controller:state` events: what CNCjs made of the status reports.
//
// FILE must move only in absolute coordinates (G90) and set X, Y and Z: where it leaves the
// machine is then where its last moves go, wherever it started (`endOfFile` of drive.js).
//
// The steps (all by default, in this order):
//
//   connect  open PTY as a Grbl controller at 115200 baud. A grbl board prints its banner
//            when the port opens; a Forja link starts in the RepRap dialect and prints none,
//            so CNCjs polls with `?` 2 s after it opened the port: the status report makes it
//            ready, and it sends `$$`. CNCjs's state then shows the machine Idle and its
//            position, and its settings the `$$` lines
//   jog      `$J=G91 X5 F1000` through CNCjs's console (`gcode`): answered `ok`, and CNCjs's
//            state shows X 5 mm further and the machine Idle again
//   job      load FILE (`gcode:load`) and run it (`gcode:start`). Once CNCjs's state shows it
//            running (`Run`): hold (`feedhold`, `!`) until the state shows `Hold:0`, see the
//            position stay put for a second, resume (`cyclestart`, `~`) until the state shows
//            `Run` and the position moving again, and raise the feed override by 10 %
//            (`feedOverride`, 0x91) until a status report's `Ov:` shows it; then wait until
//            the workflow is idle again with every line sent and answered and no `error:` or
//            `ALARM:` line. CNCjs's state then shows the machine Idle where FILE leaves it
//   reset    run FILE again; while it runs, raise the feed override by 10 % and reset (`reset`,
//            0x18). CNCjs must see the banner again (its settings take the version from it),
//            `ALARM:3` and the state `Alarm` (motion was cut), the feed override back at 100 %,
//            and no answer to the lines that were waiting (grbl drops them, and CNCjs cleared
//            its count); then unlock (`unlock`, `$X`): `[MSG:Caution: Unlocked]`, `ok`, and the
//            state Idle
//   again    run FILE once more, to its end, as `job` does without the hold: after the reset
//            the machine goes where FILE leaves it
//
// Prints `cncjs: <step> ok …` per step, or `FAILED: <step>: <why>` and the failure report with
// CNCjs's last states, and exits 1 at the first failure. At the end, whatever happened:
// `cncjs: firmware errors N` with each `error:` line, `cncjs: alarms N` with each `ALARM:`
// line the firmware sent, and `cncjs: lines CNCjs's Grbl parser does not know N` with each
// line from the first status report on that is none of grbl's (CNCjs's `GrblLineParser`
// finds no type for it), and how often it came.
'use strict';

const fs = require('fs');
const path = require('path');
const { Failed, endOfFile, run, workflowEvents } = require('./drive.js');

// The banner grbl 1.1h prints at a reset, and the version CNCjs takes from it.
const BANNER = /^Grbl 1\.1h \['\$' for help\]$/;
const VERSION = '1.1h';
// The jog of the `jog` step.
const JOG = '$J=G91 X5 F1000';
const JOG_MM = 5;
// How long the `job` step watches the position while the machine is held.
const HELD_MS = 1000;
// How long the `reset` step lets the program run before it resets it.
const RESET_AFTER_MS = 1000;
// How long a program may take to its end.
const PROGRAM_MS = 60000;
// Positions agree when closer than this, mm: less than a step (1/80 mm on X and Y).
const TOLERANCE_MM = 0.01;

// The status part of a CNCjs state: `activeState`, `subState`, `mpos`, `ov` …
function status(state) {
  return (state && state.status) || {};
}

// The machine position of a state, in mm.
function mpos(state) {
  const p = status(state).mpos || {};
  return { X: Number(p.x), Y: Number(p.y), Z: Number(p.z), A: Number(p.a) };
}

function samePosition(a, b) {
  return ['X', 'Y', 'Z', 'A'].every((axis) => Math.abs(a[axis] - b[axis]) < TOLERANCE_MM);
}

// The feed override a state shows, percent (CNCjs keeps the last `Ov:` a report carried).
function feedOverride(state) {
  return (status(state).ov || [])[0];
}

// A state as one line: `Hold:0 MPos 1.000,2.000,3.000,0.000 FS 600,12000 Ov 110 Ln 20`.
function describe(state) {
  const s = status(state);
  const p = s.mpos || {};
  const sub = s.activeState === 'Hold' || s.activeState === 'Door' ? `:${s.subState}` : '';
  return (
    `${s.activeState}${sub} MPos ${p.x},${p.y},${p.z},${p.a} FS ${s.feedrate},${s.spindle} ` +
    `Ov ${(s.ov || []).join(',')} Ln ${s.ln}`
  );
}

function where(p) {
  return `X${p.X} Y${p.Y} Z${p.Z} A${p.A}`;
}

// Wait for the first state CNCjs sent since `since` (an index of its states) that `test`
// passes, and return it. `guard`, when given, is called first on every check and throws when
// waiting is pointless (the program ended).
function waitState(cnc, since, test, ms, what, guard) {
  return cnc.until(
    () => {
      if (guard) guard();
      const found = cnc.states.slice(since).find(({ state }) => test(status(state), state));
      return found && found.state;
    },
    ms,
    `${what} in CNCjs's state`,
  );
}

// What CNCjs's console showed since `shown` (an index of its lines) of the error it paused
// the workflow on: the line it took the error for, `> line (ln=N)`, and `error:N (…)`.
function blamed(cnc, shown) {
  return JSON.stringify(cnc.shownAll.slice(shown).filter((l) => /\(ln=\d+\)$|^error:/.test(l)));
}

// A guard for `waitState`: throws when the program `started` (`startProgram`) stopped before
// `what`: its workflow idle again, or paused on an error.
function stillRunning(cnc, { flow, shown }, what) {
  return () => {
    if (cnc.workflow === 'paused') {
      throw new Failed(
        `the workflow paused before ${what}, its console showing ${blamed(cnc, shown)}`,
      );
    }
    if (cnc.workflow === 'idle' && cnc.workflowHistory.slice(flow).includes('running')) {
      throw new Failed(
        `the program ended before ${what} (workflow ${workflowEvents(cnc, flow)}): ` +
          'it is too short for this step at this time scale',
      );
    }
  };
}

// The lines received in `wire[from, to)` less the status reports and the answers to CNCjs's
// `$G` polls, which it writes unlogged: a `[GC:…]` line and the `ok` after it.
function messages(cnc, from, to) {
  const out = [];
  let parserState = false;
  for (const e of cnc.wire.slice(from, to)) {
    if (e.dir !== '<' || e.line.startsWith('<')) continue;
    if (e.line.startsWith('[GC:')) {
      parserState = true;
    } else if (parserState && e.line === 'ok') {
      parserState = false;
    } else {
      out.push(e.line);
    }
  }
  return out;
}

// The answers (`ok`, `error:N`) among `messages`.
function answers(cnc, from, to) {
  return messages(cnc, from, to).filter((line) => line === 'ok' || line.startsWith('error:'));
}

// The program of `--program`: its name, its text and where it leaves X, Y and Z.
function program(cnc) {
  const file = cnc.options.program;
  const text = fs.readFileSync(file, 'utf8');
  const end = endOfFile(text);
  for (const axis of ['X', 'Y', 'Z']) {
    if (end[axis] === null) {
      throw new Failed(`${file} never sets ${axis}: where it ends is not known`);
    }
  }
  if (/\bG91\b/i.test(text.replace(/\([^)]*\)/g, '').replace(/;.*$/gm, ''))) {
    throw new Failed(
      `${file} moves in relative coordinates (G91): where it ends depends on where it starts`,
    );
  }
  return { name: path.basename(file), text, end };
}

// Load and start the program; what the sender said of it, and where the workflow history,
// the serial lines, the states and the console lines stood before it.
async function startProgram(cnc, prog) {
  const marks = {
    flow: cnc.workflowHistory.length,
    wire: cnc.wire.length,
    states: cnc.states.length,
    shown: cnc.shownAll.length,
  };
  const loaded = await cnc.load(prog.name, prog.text);
  cnc.command('gcode:start');
  return { loaded, ...marks };
}

// Wait until the started program ends: the workflow idle again with every line sent and
// answered (CNCjs goes idle once its sender is done and the status reports show the machine
// Idle), no `error:` and no `ALARM:` line since it started, and CNCjs's state Idle where the
// program leaves the machine, A where it was (the program never moves it).
async function finishProgram(cnc, prog, started, a0) {
  const { loaded, flow, wire, shown } = started;
  await cnc.until(
    () => {
      if (cnc.workflow === 'paused') {
        throw new Failed(
          `the workflow paused at ${cnc.sender && cnc.sender.received}/${loaded.total}, its ` +
            `console showing ${blamed(cnc, shown)}; firmware lines: ` +
            JSON.stringify(messages(cnc, wire)),
        );
      }
      return cnc.workflow === 'idle' && cnc.workflowHistory.slice(flow).includes('running');
    },
    PROGRAM_MS,
    `end of ${prog.name} (workflow idle after running)`,
  );
  const last = cnc.senderBeforeIdle || {};
  if (last.total !== loaded.total || last.sent !== last.total || last.received !== last.total) {
    throw new Failed(
      `the workflow went idle with ${last.received} answered and ${last.sent} sent of ` +
        `${last.total} lines (${loaded.total} loaded)`,
    );
  }
  const faults = cnc.received(wire).filter((line) => /^(error:|ALARM:)/.test(line));
  if (faults.length > 0) {
    throw new Failed(`the firmware sent ${JSON.stringify(faults)} during ${prog.name}`);
  }
  const state = cnc.state;
  const at = mpos(state);
  const expected = { ...prog.end, A: a0 };
  if (status(state).activeState !== 'Idle' || !samePosition(at, expected)) {
    throw new Failed(
      `after ${prog.name} CNCjs's state shows ${describe(state)}; the program leaves the ` +
        `machine Idle at ${where(expected)}`,
    );
  }
  return { last, state };
}

async function stepConnect(cnc) {
  const opened = Date.now();
  await cnc.open();
  const first = await cnc.until(
    () => cnc.states.find(({ state }) => status(state).activeState),
    15000,
    "controller:state with a status report (CNCjs polls with `?` 2 s after it opened the port " +
      'and saw no banner)',
  );
  const seconds = ((first.at - opened) / 1000).toFixed(1);
  const report = cnc.received(0).find((line) => line.startsWith('<'));
  const before = cnc.received(0).slice(0, cnc.received(0).indexOf(report));
  const settings = await cnc.until(
    () => {
      const s = cnc.settings.settings || {};
      return s.$100 !== undefined && s;
    },
    10000,
    'controller:settings with the `$$` lines (CNCjs sends `$$` on its first status report)',
  );
  const state = cnc.state;
  if (status(state).activeState !== 'Idle') {
    throw new Failed(`the router starts ${describe(state)}, not Idle: ${report}`);
  }
  const shown = Object.entries(settings)
    .filter(([name]) => ['$100', '$110', '$120', '$130'].includes(name))
    .map(([name, value]) => `${name}=${value}`);
  console.log(
    `cncjs: connect ok (first status report ${seconds} s after the port opened: "${report}", ` +
      `after ${JSON.stringify(before)}; CNCjs's state ${describe(state)}; \`$$\`: ` +
      `${Object.keys(settings).length} settings, ${shown.join(' ')})`,
  );
}

async function stepJog(cnc) {
  const state = cnc.state;
  if (status(state).activeState !== 'Idle') {
    throw new Failed(`the machine is not Idle before the jog: ${describe(state)}`);
  }
  const before = mpos(state);
  const wire = cnc.wire.length;
  const since = cnc.states.length;
  cnc.gcode(JOG);
  const target = before.X + JOG_MM;
  const after = await waitState(
    cnc,
    since,
    (s, st) => s.activeState === 'Idle' && Math.abs(mpos(st).X - target) < TOLERANCE_MM,
    15000,
    `Idle at X${target.toFixed(3)} after ${JOG}`,
  );
  const answer = await cnc.until(
    () => {
      const written = cnc.wire.findIndex((e, i) => i >= wire && e.dir === '>' && e.line === JOG);
      return written >= 0 && answers(cnc, written + 1)[0];
    },
    5000,
    `answer to ${JOG}`,
  );
  if (answer !== 'ok') {
    throw new Failed(`${JOG} was answered ${answer}`);
  }
  const seen = [...new Set(cnc.states.slice(since).map(({ state: s }) => status(s).activeState))];
  const moved = mpos(after);
  for (const axis of ['Y', 'Z', 'A']) {
    if (Math.abs(moved[axis] - before[axis]) >= TOLERANCE_MM) {
      throw new Failed(`${JOG} moved ${axis}: ${where(before)} -> ${where(moved)}`);
    }
  }
  console.log(
    `cncjs: jog ok (${JOG} answered "${answer}"; CNCjs's state ${where(before)} -> ` +
      `${where(moved)}, states ${seen.join(' -> ')})`,
  );
}

async function stepJob(cnc) {
  const prog = program(cnc);
  const a0 = mpos(cnc.state).A;
  const started = await startProgram(cnc, prog);
  const guard = (what) => stillRunning(cnc, started, what);
  const running = await waitState(
    cnc,
    started.states,
    (s) => s.activeState === 'Run',
    15000,
    'Run after gcode:start',
    guard('it showed Run'),
  );
  // Hold: `!`, until the machine is at rest on its path (`Hold:0`).
  let from = cnc.states.length;
  cnc.command('feedhold');
  const held = await waitState(
    cnc,
    from,
    (s) => s.activeState === 'Hold' && s.subState === 0,
    10000,
    'Hold:0 after feedhold (!)',
    guard('the hold'),
  );
  const heldAt = mpos(held);
  from = cnc.states.length;
  await cnc.sleep(HELD_MS);
  const moved = ({ state }) =>
    status(state).activeState !== 'Hold' || !samePosition(mpos(state), heldAt);
  const drift = cnc.states.slice(from).find(moved);
  if (drift) {
    throw new Failed(
      `held at ${where(heldAt)}, CNCjs's state then showed ${describe(drift.state)} before ` +
        'cyclestart',
    );
  }
  // Resume: `~`, until the machine runs again and has left the place it held at.
  from = cnc.states.length;
  cnc.command('cyclestart');
  const resumed = await waitState(
    cnc,
    from,
    (s, st) => s.activeState === 'Run' && !samePosition(mpos(st), heldAt),
    10000,
    `Run away from ${where(heldAt)} after cyclestart (~)`,
    guard('the resume'),
  );
  // Feed override +10 %: 0x91, until a status report's `Ov:` shows it.
  const wire = cnc.wire.length;
  const [overrideBefore, overrideTarget] = await raiseFeedOverride(cnc, guard);
  const ovLine = cnc.received(wire).find((line) => /\|Ov:/.test(line));
  const { last, state } = await finishProgram(cnc, prog, started, a0);
  console.log(
    `cncjs: job ok (${prog.name}: ${last.received}/${last.total} lines answered, workflow ` +
      `${workflowEvents(cnc, started.flow)}; CNCjs's state ${describe(running)}, held ` +
      `${describe(held)} and still for ${HELD_MS} ms, resumed ${describe(resumed)}, feed ` +
      `override ${overrideBefore} -> ${overrideTarget} % ("${ovLine}"); at the end ` +
      `${describe(state)})`,
  );
}

// Raise the feed override by 10 % (CNCjs's `feedOverride`, byte 0x91) and wait until a
// status report's `Ov:` shows it; the percentages before and after.
async function raiseFeedOverride(cnc, guard) {
  const before = feedOverride(cnc.state) || 100;
  const target = Math.min(before + 10, 200);
  const from = cnc.states.length;
  guard('the feed override')();
  cnc.command('feedOverride', 10);
  await waitState(
    cnc,
    from,
    (s, st) => feedOverride(st) === target,
    10000,
    `feed override ${target} % (Ov:${target}) after feedOverride +10 (0x91)`,
    guard('the feed override showed'),
  );
  return [before, target];
}

async function stepReset(cnc) {
  const prog = program(cnc);
  const started = await startProgram(cnc, prog);
  const guard = (what) => stillRunning(cnc, started, what);
  await waitState(
    cnc,
    started.states,
    (s) => s.activeState === 'Run',
    15000,
    'Run after gcode:start',
    guard('it showed Run'),
  );
  await cnc.sleep(RESET_AFTER_MS);
  const [, overrideTarget] = await raiseFeedOverride(cnc, guard);
  let from = cnc.states.length;
  const before = cnc.state;
  if (status(before).activeState !== 'Run') {
    throw new Failed(`the machine does not run when the reset is to cut it: ${describe(before)}`);
  }
  const sender = cnc.sender || {};
  const pending = `${sender.sent - sender.received} of ${sender.sent} lines sent unanswered`;
  // Reset: 0x18.
  from = cnc.states.length;
  const wire = cnc.wire.length;
  cnc.command('reset');
  const banner = await cnc.until(
    () => cnc.received(wire).find((line) => BANNER.test(line)),
    10000,
    `the banner "Grbl ${VERSION} ['$' for help]" after the reset (0x18)`,
  );
  await cnc.until(
    () => cnc.settings.version === VERSION,
    5000,
    `controller:settings with version ${VERSION} (CNCjs takes it from the banner)`,
  );
  const alarm = await cnc.until(
    () => cnc.received(wire).find((line) => line.startsWith('ALARM:')),
    10000,
    'an ALARM: line after the reset (it cut the motion)',
  );
  if (alarm !== 'ALARM:3') {
    throw new Failed(
      `the reset during motion raised ${alarm}; grbl's is ALARM:3 (reset while in motion)`,
    );
  }
  const alarmed = await waitState(cnc, from, (s) => s.activeState === 'Alarm', 10000, 'Alarm');
  await waitState(
    cnc,
    from,
    (s, st) => feedOverride(st) === 100,
    10000,
    'the feed override back at 100 % (Ov:100) after the reset',
  );
  await cnc.until(() => cnc.workflow === 'idle', 5000, 'idle workflow after the reset');
  const afterReset = messages(cnc, wire);
  // Unlock: `$X`.
  const unlockAt = cnc.wire.length;
  const stray = answers(cnc, wire, unlockAt);
  if (stray.length > 0) {
    throw new Failed(
      `after the reset the firmware answered ${JSON.stringify(stray)} before \`$X\`: the ` +
        `lines waiting at a reset (${pending}) are dropped unanswered, as grbl flushes its ` +
        'receive buffer, and CNCjs cleared its count',
    );
  }
  from = cnc.states.length;
  cnc.command('unlock');
  const unlocked = await cnc.until(
    () => {
      const lines = messages(cnc, unlockAt);
      const at = lines.indexOf('[MSG:Caution: Unlocked]');
      const ok = lines.indexOf('ok', at);
      return at >= 0 && ok >= 0 && lines.slice(at, ok + 1);
    },
    10000,
    '[MSG:Caution: Unlocked] and ok after $X',
  );
  const idle = await waitState(cnc, from, (s) => s.activeState === 'Idle', 10000, 'Idle after $X');
  console.log(
    `cncjs: reset ok (reset while ${describe(before)} with ${pending}: "${banner}" (settings ` +
      `version ${cnc.settings.version}), "${alarm}", CNCjs's state ${describe(alarmed)}, the ` +
      `firmware's lines ${JSON.stringify(afterReset)}, no answer to the dropped lines; $X: ` +
      `${JSON.stringify(unlocked)}, state ${describe(idle)})`,
  );
}

async function stepAgain(cnc) {
  const prog = program(cnc);
  const a0 = mpos(cnc.state).A;
  const from = mpos(cnc.state);
  const started = await startProgram(cnc, prog);
  const { last, state } = await finishProgram(cnc, prog, started, a0);
  console.log(
    `cncjs: again ok (${prog.name} from ${where(from)}: ${last.received}/${last.total} lines ` +
      `answered, workflow ${workflowEvents(cnc, started.flow)}; CNCjs's state ` +
      `${describe(state)})`,
  );
}

// The lines received from the first status report on (the link speaks the grbl dialect from
// then on) that CNCjs's own parser of grbl's lines does not know (its `others`, which it only
// shows in its console).
function unknownLines(cnc) {
  const file = path.join(cnc.modules, 'cncjs/dist/cncjs/server/controllers/Grbl/GrblLineParser');
  const Parser = require(file).default;
  const parser = new Parser();
  const lines = cnc.received(0).filter((line) => line);
  const first = lines.findIndex((line) => line.startsWith('<'));
  return first < 0 ? [] : lines.slice(first).filter((line) => parser.parse(line).type === null);
}

function grblSummary(cnc) {
  const lines = cnc.received(0);
  const errors = lines.filter((line) => line.startsWith('error:'));
  console.log(`cncjs: firmware errors ${errors.length}`);
  for (const line of errors) console.log(`  ${line}`);
  const alarms = lines.filter((line) => line.startsWith('ALARM:'));
  console.log(`cncjs: alarms ${alarms.length}`);
  for (const line of alarms) console.log(`  ${line}`);
  const unknown = unknownLines(cnc);
  console.log(`cncjs: lines CNCjs's Grbl parser does not know ${unknown.length}`);
  for (const line of [...new Set(unknown)]) {
    console.log(`  ${JSON.stringify(line)} x${unknown.filter((l) => l === line).length}`);
  }
}

run({
  controller: 'Grbl',
  steps: {
    connect: stepConnect,
    jog: stepJog,
    job: stepJob,
    reset: stepReset,
    again: stepAgain,
  },
  required: ['program'],
  summary: grblSummary,
  describe,
});
