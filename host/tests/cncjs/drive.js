#!/usr/bin/env node
// Drive a printer with CNCjs's own server in Marlin mode, as its web interface does.
//
// Usage: node drive.js --cncjs DIR --pty PTY --job FILE --workdir DIR [--seconds N]
//                      [--steps LIST]
//
// Starts the CNCjs server installed under `--cncjs` (`npm install --prefix DIR cncjs@1`) on a
// free port of 127.0.0.1, with a fresh configuration file in the work directory: a known
// `secret` and no user accounts, so that a token signed with that secret is all the server
// asks for, and errors pause a job (`state.controller.exception.ignoreErrors` false, CNCjs's
// default). The token is signed with the `jsonwebtoken` package CNCjs itself uses, and the
// driver talks to the server with the `socket.io-client` CNCjs's web interface uses, through
// the events and commands of CNCjs 1.x (`open`, `command`, `close`; `controller:settings`,
// `controller:state`, `workflow:state`, `sender:status`, `serialport:read`).
//
// The serial traffic is read from CNCjs's own log (`-vvv`: `controller:Marlin < line` for every
// line received, `> line` for every line its sender and feeder write). Its `serialport:read`
// events, which its console shows, leave out the `ok`, position and temperature lines that
// answer its sender and its own polls, and they attribute an answer to the last line written:
// when the feeder's queue empties, CNCjs writes its next M114/M105 poll right behind the
// feeder's last line, and the answer to that line is then taken for the poll's and not shown.
//
// The server, the socket, the log and the step runner are shared with `drive_grbl.js`, which
// drives a router with CNCjs in its Grbl mode: this file is also a module (`run`, `Cncjs`,
// `Failed`, `endOfFile`, `workflowEvents`).
//
// The steps (all by default, in this order):
//
//   connect   open PTY as a Marlin controller at 115200 baud; CNCjs sends M115 and is ready
//             on the `FIRMWARE_NAME:` line; its state then shows the position (its own M114
//             polls) and the temperatures (its M105 polls)
//   position  send M114, then `G91`, `G0 X5`, `G90`; CNCjs's state shows X moved by 5 mm
//   fault     run a small job on the unhomed machine whose third move drives X past its
//             minimum switch: the firmware stops the machine with an `Error:` line and the
//             CNCjs workflow pauses on it; then stop the workflow and clear the fault (M999)
//   job       load FILE (`gcode:load`), start it (`gcode:start`) and wait until the workflow
//             is idle again with every line of it sent and answered and no `Error:` line;
//             then M114 shows where the file leaves the X and Y axes
//   finish    run a job of four slow moves, which the planner takes at once: CNCjs ends a job
//             with `G4 S0.5` (its `%wait`, which Marlin answers once the moves before it are
//             done) and then waits for M114 to stop changing, so its workflow must go idle
//             only once the machine is at rest: M114 at that moment and after M400 agree
//
// Prints `cncjs: <step> ok …` per step, or `FAILED: <step>: <why>` and then the last lines CNCjs
// logged, the last serial lines and the last lines its console showed, and exits 1 at the first
// failure. At the end, whatever happened: `cncjs: firmware errors N` with each `Error:` line,
// `cncjs: unknown commands N` with the commands the firmware said it does not have, and
// `cncjs: refusals N` with each `echo:E<code>` refusal. The server is stopped before the driver
// exits (SIGTERM, then SIGKILL); it also exits by itself when the driver is killed
// (`exit-with-parent.js`).
'use strict';

const childProcess = require('child_process');
const fs = require('fs');
const path = require('path');

const SECRET = 'forja-cncjs-acceptance';
const BAUD_RATE = 115200;
// How many lines of CNCjs's log and of the serial traffic a failure report shows.
const TAIL_LINES = 40;

class Failed extends Error {}

// The options of the command line: `--name value` pairs, those in `required` not empty, and
// `--steps` (a comma-separated list, by default all of `steps`) a list of some of `steps`.
function parseArgs(argv, steps, required) {
  const options = { seconds: 170, steps: steps.join(',') };
  for (let i = 0; i < argv.length; i += 2) {
    const name = argv[i];
    const value = argv[i + 1];
    if (!name.startsWith('--') || value === undefined) {
      throw new Failed(`bad arguments near ${JSON.stringify(name)}`);
    }
    options[name.slice(2)] = value;
  }
  for (const name of ['cncjs', 'pty', 'workdir', ...required]) {
    if (!options[name]) {
      throw new Failed(`--${name} is required`);
    }
  }
  options.seconds = Number(options.seconds);
  options.steps = options.steps.split(',').filter((s) => s);
  for (const step of options.steps) {
    if (!steps.includes(step)) {
      throw new Failed(`unknown step ${JSON.stringify(step)} (known: ${steps.join(', ')})`);
    }
  }
  return options;
}

// The last `limit` items pushed.
class Tail {
  constructor(limit) {
    this.limit = limit;
    this.items = [];
  }

  push(item) {
    this.items.push(item);
    if (this.items.length > this.limit) {
      this.items.shift();
    }
  }
}

// Where the X, Y and Z axes are after `text`, read as grbl and Marlin read it: G90/G91, G92,
// and the moves G0, G1, G2 and G3 (an arc ends at its X Y Z words), whose mode stays in force
// for the lines that name only axes (CAM programs write `X40. F600.` after a `G1`; the slicers
// name G0/G1 on every move). Comments in parentheses and after `;` are left out, and so are
// the axis words of the G codes that take them for something else than a move (`G4`, `G10`,
// `G28`, `G30`). null for an axis the file never sets.
function endOfFile(text) {
  const at = { X: null, Y: null, Z: null };
  const moves = ['G0', 'G1', 'G2', 'G3'];
  const notMoves = ['G4', 'G10', 'G28', 'G30'];
  let relative = false;
  let motion = null;
  for (const raw of text.split('\n')) {
    const code = raw.replace(/;.*$/, '').replace(/\([^)]*\)/g, '').trim().toUpperCase();
    const words = code.match(/[A-Z][-+]?[0-9.]+/g) || [];
    const value = (letter) => {
      const word = words.find((w) => w[0] === letter);
      return word === undefined ? undefined : Number(word.slice(1));
    };
    // `G01` is `G1`, `G00` is `G0`.
    const gs = words.filter((w) => w[0] === 'G').map((w) => `G${Number(w.slice(1))}`);
    if (gs.includes('G90')) relative = false;
    if (gs.includes('G91')) relative = true;
    motion = gs.filter((g) => moves.includes(g)).pop() || motion;
    const setting = gs.includes('G92');
    const move = motion !== null && !setting && !gs.some((g) => notMoves.includes(g));
    for (const axis of ['X', 'Y', 'Z']) {
      const v = value(axis);
      if (v === undefined) continue;
      if (setting) {
        at[axis] = v;
      } else if (move) {
        at[axis] = relative && at[axis] !== null ? at[axis] + v : v;
      }
    }
  }
  return at;
}

// The CNCjs server, a socket.io client connected to it, and what it reported. `controller` is
// the type of controller CNCjs opens the port as (`Marlin`, `Grbl`), which also names its log
// lines.
class Cncjs {
  constructor(options, deadline, controller) {
    this.options = options;
    this.controller = controller;
    this.deadline = deadline;
    this.modules = path.resolve(options.cncjs, 'node_modules');
    this.server = null;
    this.serverExited = null;
    this.socket = null;
    this.logFile = path.join(options.workdir, 'cncjs.log');
    this.log = new Tail(TAIL_LINES);
    // Every line exchanged with the firmware as CNCjs logged it: `{ dir: '<' | '>', line }`.
    this.wire = [];
    // The last of them, and the commands this driver gave, for a failure report.
    this.serial = new Tail(TAIL_LINES);
    // The lines CNCjs's console showed (`serialport:read`), and the last of them.
    this.shownAll = [];
    this.shown = new Tail(TAIL_LINES);
    this.settings = {};
    this.state = null;
    this.stateUpdates = 0;
    // Every `controller:state` CNCjs sent, with when it came: `{ at, state }`.
    this.states = [];
    this.workflow = null;
    this.workflowHistory = [];
    this.sender = null;
    this.senderBeforeIdle = null;
    this.closing = false;
    this.broken = null;
    this.waiters = [];
  }

  remainingMs() {
    return this.deadline - Date.now();
  }

  // Start the server on a free port and wait until it listens.
  async start() {
    const rc = path.join(this.options.workdir, 'cncrc');
    fs.writeFileSync(
      rc,
      JSON.stringify(
        {
          secret: SECRET,
          state: {
            allowAnonymousUsageDataCollection: false,
            checkForUpdates: false,
            controller: { exception: { ignoreErrors: false } },
          },
        },
        null,
        2,
      ),
    );
    const bin = path.join(this.modules, 'cncjs', 'bin', 'cncjs');
    if (!fs.existsSync(bin)) {
      throw new Failed(`no CNCjs at ${bin}`);
    }
    const log = fs.openSync(this.logFile, 'w');
    this.traffic = new RegExp(` controller:${this.controller} ([<>]) (.*)$`);
    this.server = childProcess.spawn(
      process.execPath,
      [
        '--require',
        path.join(__dirname, 'exit-with-parent.js'),
        bin,
        '--host',
        '127.0.0.1',
        '--port',
        '0',
        '--config',
        rc,
        '-vvv',
      ],
      { stdio: ['ignore', 'pipe', 'pipe'], env: { ...process.env, FORCE_COLOR: '0' } },
    );
    this.serverExited = new Promise((resolve) => this.server.on('exit', resolve));
    this.server.on('close', () => fs.closeSync(log));
    this.server.on('exit', (code, signal) => {
      if (!this.closing) {
        this.break(`the CNCjs server exited (code ${code}, signal ${signal})`);
      }
    });
    const listening = new Promise((resolve) => {
      let pending = '';
      const take = (chunk) => {
        fs.writeSync(log, chunk);
        pending += chunk.toString();
        const lines = pending.split('\n');
        pending = lines.pop();
        for (const line of lines) {
          // eslint-disable-next-line no-control-regex
          const plain = line.replace(/\x1b\[[0-9;]*m/g, '');
          this.log.push(plain);
          const traffic = plain.match(this.traffic);
          if (traffic) {
            const entry = { dir: traffic[1], line: traffic[2].replace(/\s+$/, '') };
            this.wire.push(entry);
            this.serial.push(`${entry.dir} ${entry.line}`);
            this.changed();
          }
          const found = plain.match(/Starting the server at http:\/\/127\.0\.0\.1:(\d+)/);
          if (found) resolve(Number(found[1]));
        }
      };
      this.server.stdout.on('data', take);
      this.server.stderr.on('data', take);
    });
    this.port = await this.race(listening, 30000, 'the CNCjs server to listen');
    return this.port;
  }

  // Connect to the server with a token signed as CNCjs signs its own.
  async connect() {
    const jwt = require(path.join(this.modules, 'jsonwebtoken'));
    const io = require(path.join(this.modules, 'socket.io-client'));
    const token = jwt.sign({ id: '', name: 'forja' }, SECRET, { expiresIn: '1h' });
    this.socket = io(`http://127.0.0.1:${this.port}`, {
      query: { token },
      reconnection: false,
      transports: ['websocket'],
    });
    const connected = new Promise((resolve, reject) => {
      this.socket.on('connect', resolve);
      this.socket.on('connect_error', (err) => reject(new Failed(`connect_error: ${err}`)));
      this.socket.on('error', (err) => reject(new Failed(`socket error: ${JSON.stringify(err)}`)));
    });
    this.listen();
    await this.race(connected, 15000, 'the socket.io connection');
  }

  listen() {
    const s = this.socket;
    s.on('disconnect', (reason) => {
      if (!this.closing) this.break(`the server closed the socket (${reason})`);
    });
    s.on('serialport:error', (e) => this.break(`serialport:error ${JSON.stringify(e)}`));
    s.on('serialport:close', (e) => {
      if (!this.closing) this.break(`serialport:close ${JSON.stringify(e)}`);
    });
    s.on('serialport:read', (data) => {
      for (const line of String(data).split('\n')) {
        if (!line.trim()) continue;
        this.shownAll.push(line.replace(/\s+$/, ''));
        this.shown.push(line.replace(/\s+$/, ''));
      }
    });
    s.on('controller:settings', (type, settings) => {
      this.settings = settings || {};
      this.changed();
    });
    s.on('controller:state', (type, state) => {
      this.state = state;
      this.stateUpdates += 1;
      this.states.push({ at: Date.now(), state });
      this.changed();
    });
    s.on('sender:status', (status) => {
      this.sender = status;
      this.changed();
    });
    s.on('workflow:state', (state) => {
      if (state === 'idle') this.senderBeforeIdle = this.sender;
      this.workflow = state;
      this.workflowHistory.push(state);
      this.changed();
    });
  }

  // A condition that no wait can meet any more: every wait fails with it.
  break(why) {
    if (this.broken) return;
    this.broken = why;
    this.changed();
  }

  changed() {
    for (const waiter of [...this.waiters]) {
      waiter.check();
    }
  }

  // Resolve with `promise`, or fail after `ms` (or at the overall deadline).
  race(promise, ms, what) {
    const limit = Math.min(ms, Math.max(0, this.remainingMs()));
    let timer;
    const timeout = new Promise((_, reject) => {
      timer = setTimeout(
        () => reject(new Failed(`no ${what} within ${(limit / 1000).toFixed(1)} s`)),
        limit,
      );
    });
    return Promise.race([promise, timeout]).finally(() => clearTimeout(timer));
  }

  // Wait until `test()` returns a value other than undefined/false, re-checked on every event
  // CNCjs sends; fail after `ms`, when the link breaks, or when `test` throws.
  until(test, ms, what) {
    return new Promise((resolve, reject) => {
      const limit = Math.min(ms, Math.max(0, this.remainingMs()));
      const waiter = {
        check: () => {
          if (this.broken) {
            done();
            reject(new Failed(`${this.broken} while waiting for ${what}`));
            return;
          }
          let value;
          try {
            value = test();
          } catch (err) {
            done();
            reject(err);
            return;
          }
          if (value !== undefined && value !== false && value !== null) {
            done();
            resolve(value);
          }
        },
      };
      const timer = setTimeout(() => {
        done();
        reject(new Failed(`no ${what} within ${(limit / 1000).toFixed(1)} s`));
      }, limit);
      const done = () => {
        clearTimeout(timer);
        this.waiters = this.waiters.filter((w) => w !== waiter);
      };
      this.waiters.push(waiter);
      waiter.check();
    });
  }

  // Wait `ms` (less if the overall deadline is nearer).
  sleep(ms) {
    const limit = Math.min(ms, Math.max(0, this.remainingMs()));
    return new Promise((resolve) => setTimeout(resolve, limit));
  }

  // Open the port as this controller at 115200 baud.
  async open() {
    const pty = this.options.pty;
    const options = { controllerType: this.controller, baudrate: BAUD_RATE };
    const opened = new Promise((resolve, reject) => {
      this.socket.emit('open', pty, options, (err) =>
        err ? reject(new Failed(`open ${pty}: ${JSON.stringify(err.message || err)}`)) : resolve(),
      );
    });
    await this.race(opened, 15000, `answer to open ${pty}`);
  }

  // Load `text` as the program `name` (`gcode:load`); what the sender says of it.
  load(name, text) {
    return this.commandWithAnswer(10000, 'gcode:load', 'gcode:load', name, text, {});
  }

  // A CNCjs command with its callback answer (`gcode:load`), or without one.
  command(...args) {
    this.socket.emit('command', this.options.pty, ...args);
  }

  commandWithAnswer(ms, what, ...args) {
    return this.race(
      new Promise((resolve, reject) => {
        this.command(...args, (err, data) =>
          err ? reject(new Failed(`${what}: ${JSON.stringify(err)}`)) : resolve(data),
        );
      }),
      ms,
      `answer to ${what}`,
    );
  }

  // Lines received from the firmware since `since` (an index of `wire`).
  received(since) {
    return this.wire
      .slice(since)
      .filter((e) => e.dir === '<')
      .map((e) => e.line);
  }

  // G-code through CNCjs's feeder, as its console sends it.
  gcode(text) {
    this.serial.push(`(the driver sends ${JSON.stringify(text)} through CNCjs)`);
    this.command('gcode', text);
  }

  // Send `command` and wait for the first line matching `answer` after CNCjs wrote it, and the
  // `ok` after that line. The firmware answers in order, and CNCjs writes a line of its feeder
  // only after the answer to every line before it, so the lines after it answer it (or a poll
  // CNCjs wrote behind it).
  async ask(command, answer, ms, what) {
    const since = this.wire.length;
    this.gcode(command);
    return this.until(
      () => {
        const wire = this.wire.slice(since);
        const sent = wire.findIndex((e) => e.dir === '>' && e.line === command);
        if (sent < 0) return undefined;
        const after = wire.slice(sent + 1).filter((e) => e.dir === '<');
        const at = after.findIndex((e) => answer.test(e.line));
        return at >= 0 && after.slice(at).some((e) => e.line === 'ok') && after[at].line;
      },
      ms,
      what,
    );
  }

  // Send M114 and wait for the position line it answers.
  async askPosition(what) {
    const line = await this.ask('M114', /^X:/, 15000, `M114 position line and ok (${what})`);
    const pos = {};
    for (const m of line.split(/\s+Count\s+/)[0].matchAll(/([XYZE]):(-?[0-9.]+)/g)) {
      pos[m[1]] = Number(m[2]);
    }
    return { pos, line };
  }

  // Close the port, disconnect, and stop the server: SIGTERM, then SIGKILL after 5 s.
  async stop() {
    this.closing = true;
    if (this.socket && this.socket.connected) {
      await this.race(
        new Promise((resolve) => this.socket.emit('close', this.options.pty, resolve)),
        5000,
        'answer to close',
      ).catch(() => {});
      this.socket.close();
    }
    if (this.server && this.server.exitCode === null && this.server.signalCode === null) {
      this.server.kill('SIGTERM');
      const exited = await Promise.race([
        this.serverExited.then(() => true),
        new Promise((resolve) => setTimeout(() => resolve(false), 5000)),
      ]);
      if (!exited) {
        this.server.kill('SIGKILL');
        await this.serverExited;
      }
    }
  }

  killNow() {
    if (this.server && this.server.exitCode === null && this.server.signalCode === null) {
      this.server.kill('SIGKILL');
    }
  }
}

function workflowEvents(cnc, since) {
  return cnc.workflowHistory.slice(since).join(' -> ') || '(none)';
}

async function stepConnect(cnc) {
  await cnc.open();
  const firmware = await cnc.until(
    () => cnc.settings.firmwareName,
    20000,
    'FIRMWARE_NAME line (CNCjs is ready on it)',
  );
  const firmwareLine = cnc.received(0).find((line) => line.startsWith('FIRMWARE_NAME:'));
  // The position and temperatures come from CNCjs's own M114 and M105 polls.
  const state = await cnc.until(
    () =>
      cnc.state &&
      cnc.state.extruder &&
      cnc.state.extruder.deg !== undefined &&
      cnc.state.heatedBed &&
      cnc.state.heatedBed.deg !== undefined &&
      cnc.state,
    20000,
    'controller:state with the temperatures of its M105 polls',
  );
  const pos = state.pos || {};
  console.log(
    `cncjs: connect ok (firmware "${firmware}": ${firmwareLine}; ` +
      `state X${pos.x} Y${pos.y} Z${pos.z} E${pos.e}, hot end ${state.extruder.deg} ` +
      `/${state.extruder.degTarget}, bed ${state.heatedBed.deg} /${state.heatedBed.degTarget})`,
  );
}

async function stepPosition(cnc) {
  const before = await cnc.askPosition('before the move');
  const x0 = before.pos.X;
  if (!Number.isFinite(x0)) {
    throw new Failed(`M114 answered ${JSON.stringify(before.line)}: no X`);
  }
  cnc.gcode('G91\nG0 X5\nG90');
  const target = x0 + 5;
  const updatesBefore = cnc.stateUpdates;
  const state = await cnc.until(
    () =>
      cnc.stateUpdates > updatesBefore &&
      Math.abs(Number(cnc.state.pos.x) - target) < 0.01 &&
      cnc.state,
    20000,
    `controller:state with pos.x ${target.toFixed(3)} (its M114 polls), last pos ` +
      JSON.stringify(cnc.state && cnc.state.pos),
  );
  console.log(
    `cncjs: position ok (M114 "${before.line}"; after G91 G0 X5 G90 CNCjs's state shows ` +
      `X${state.pos.x} Y${state.pos.y} Z${state.pos.z})`,
  );
}

// A job whose third move runs X into its minimum switch on the unhomed machine, which starts
// 100 mm from that switch (the position step moves it 5 mm further): a move of -200 mm, shorter
// than the 235 mm travel so that it is not refused as out of reach, meets the switch half way.
// The moves after it fill the planner and keep CNCjs's sender waiting for an `ok`, so that the
// fault arrives while the job runs.
function faultJob() {
  const lines = [
    '; the third move drives X past its minimum switch',
    'G91',
    'G1 X-1 F3000',
    'G1 Y-1 F3000',
    'G1 X-200 F3000',
  ];
  for (let i = 0; i < 40; i += 1) {
    lines.push(`G1 Y${i % 2 === 0 ? '0.5' : '-0.5'} F600`);
  }
  lines.push('G90');
  return lines.join('\n') + '\n';
}

async function stepFault(cnc) {
  const since = cnc.wire.length;
  const shownFrom = cnc.shownAll.length;
  const flow = cnc.workflowHistory.length;
  const loaded = await cnc.load('limit.gcode', faultJob());
  cnc.command('gcode:start');
  const state = await cnc.until(
    () => {
      if (cnc.workflow === 'idle' && cnc.workflowHistory.slice(flow).includes('running')) {
        throw new Failed(
          `the workflow ended without pausing (${workflowEvents(cnc, flow)}); ` +
            `firmware lines: ${JSON.stringify(cnc.received(since))}`,
        );
      }
      return cnc.workflow === 'paused' && cnc.workflow;
    },
    30000,
    `paused workflow after the limit move (workflow ${workflowEvents(cnc, flow)})`,
  );
  const error = cnc.received(since).find((line) => /^Error:/i.test(line));
  if (!error) {
    throw new Failed(
      `the workflow is ${state} but no Error: line came: ${JSON.stringify(cnc.received(since))}`,
    );
  }
  const hold = await cnc.until(
    () => cnc.sender && cnc.sender.hold && cnc.sender.holdReason,
    5000,
    'sender:status holding with a reason',
  );
  if (!hold.err) {
    throw new Failed(`the sender holds for ${JSON.stringify(hold)}, not for the error`);
  }
  const at = `${cnc.sender.received}/${cnc.sender.sent} of ${cnc.sender.total} lines answered/sent`;
  cnc.command('gcode:stop');
  await cnc.until(() => cnc.workflow === 'idle', 10000, 'idle workflow after gcode:stop');
  // What the firmware sent after the fault up to the next `ok`: the answer to the line that
  // was waiting when the fault came, which CNCjs counted as answered by the `Error:` line.
  const lines = cnc.received(since);
  const from = lines.indexOf(error);
  const okAt = lines.indexOf('ok', from);
  const then = lines.slice(from + 1, okAt < 0 ? undefined : okAt + 1);
  // The line CNCjs's console blames for the error (`> line (ln=N)`).
  const blamed = cnc.shownAll.slice(shownFrom).find((line) => /\(ln=\d+\)$/.test(line));
  const cleared = await cnc.ask('M999', /^ok$/, 15000, 'ok to M999');
  const after = await cnc.askPosition('after M999');
  console.log(
    `cncjs: fault ok (firmware "${error}", then ${JSON.stringify(then)}; workflow ` +
      `${workflowEvents(cnc, flow)}, paused at ${at} (${loaded.total} loaded), hold reason ` +
      `${JSON.stringify(hold.msg)}, console "${blamed}"; M999 answered "${cleared}", then ` +
      `M114 "${after.line}")`,
  );
}

async function stepJob(cnc) {
  const file = cnc.options.job;
  const text = fs.readFileSync(file, 'utf8');
  const end = endOfFile(text);
  const since = cnc.wire.length;
  const flow = cnc.workflowHistory.length;
  const loaded = await cnc.load(path.basename(file), text);
  const started = Date.now();
  cnc.command('gcode:start');
  // The rest of the time, less what the steps after it take.
  const jobMs = Math.max(0, cnc.remainingMs() - 20000);
  await cnc.until(
    () => {
      if (cnc.workflow === 'paused') {
        const errors = cnc.received(since).filter((line) => /^Error:/i.test(line));
        throw new Failed(
          `the workflow paused at ${cnc.sender && cnc.sender.received}/${loaded.total} ` +
            `(hold ${JSON.stringify(cnc.sender && cnc.sender.holdReason)}); firmware errors: ` +
            JSON.stringify(errors),
        );
      }
      return cnc.workflow === 'idle' && cnc.workflowHistory.slice(flow).includes('running');
    },
    jobMs,
    `end of ${path.basename(file)} (workflow ${workflowEvents(cnc, flow)}, sender ` +
      `${cnc.sender && cnc.sender.received}/${cnc.sender && cnc.sender.sent} of ${loaded.total})`,
  );
  const seconds = ((Date.now() - started) / 1000).toFixed(1);
  const last = cnc.senderBeforeIdle || {};
  if (last.total !== loaded.total || last.sent !== last.total || last.received !== last.total) {
    throw new Failed(
      `the workflow went idle with ${last.received} answered and ${last.sent} sent of ` +
        `${last.total} lines (${loaded.total} loaded) after ${seconds} s`,
    );
  }
  const errors = cnc.received(since).filter((line) => /^Error:/i.test(line));
  if (errors.length > 0) {
    throw new Failed(`firmware errors during the job: ${JSON.stringify(errors)}`);
  }
  const at = await cnc.askPosition('after the job');
  for (const axis of ['X', 'Y']) {
    if (end[axis] !== null && Math.abs(at.pos[axis] - end[axis]) > 0.01) {
      throw new Failed(
        `after the job M114 answers "${at.line}", the file ends at ${axis}${end[axis]}`,
      );
    }
  }
  console.log(
    `cncjs: job ok (${path.basename(file)}: ${last.received}/${last.total} lines answered in ` +
      `${seconds} s, workflow ${workflowEvents(cnc, flow)}, 0 firmware errors; M114 "${at.line}")`,
  );
}

// Four relative moves at 5 mm/s, 120 mm in all: far longer than CNCjs takes to send them and
// to see M114 stand still. Relative, so that they stay inside the travel wherever the machine is
// (after the slicer job at X0 Y235, or unhomed).
function slowJob() {
  return ['G91', 'G1 X40 F300', 'G1 Y-40', 'G1 X-20', 'G1 Y20', 'G90'].join('\n') + '\n';
}

// The `Count` part of an M114 line: the step counts, where the motors are.
function counts(line) {
  const part = line.split(/\s+Count\s+/)[1];
  return part === undefined ? line : part.trim();
}

async function stepFinish(cnc) {
  const flow = cnc.workflowHistory.length;
  const loaded = await cnc.load('slow.gcode', slowJob());
  const started = Date.now();
  cnc.command('gcode:start');
  await cnc.until(
    () => {
      if (cnc.workflow === 'paused') {
        const hold = cnc.sender && cnc.sender.holdReason;
        throw new Failed(`the workflow paused (hold ${JSON.stringify(hold)})`);
      }
      return cnc.workflow === 'idle' && cnc.workflowHistory.slice(flow).includes('running');
    },
    60000,
    `end of slow.gcode (workflow ${workflowEvents(cnc, flow)})`,
  );
  const idleAfter = ((Date.now() - started) / 1000).toFixed(1);
  const atIdle = await cnc.askPosition('when the workflow went idle');
  const waitStart = Date.now();
  await cnc.ask('M400', /^ok$/, 60000, 'ok to M400');
  const ranOn = ((Date.now() - waitStart) / 1000).toFixed(1);
  const atRest = await cnc.askPosition('after M400');
  const last = cnc.senderBeforeIdle || {};
  if (counts(atIdle.line) !== counts(atRest.line)) {
    throw new Failed(
      `CNCjs ended the job (workflow idle, ${last.received}/${loaded.total} lines answered) ` +
        `${idleAfter} s after its start while the machine was still moving: M114 then ` +
        `"${atIdle.line}", after M400 (${ranOn} s later) "${atRest.line}"; CNCjs relies on the ` +
        `ok to its final G4 S0.5 (%wait) coming after the moves before it, then on M114 ` +
        `X:/Y:/Z: standing still`,
    );
  }
  console.log(
    `cncjs: finish ok (slow.gcode idle after ${idleAfter} s with the machine at rest: ` +
      `M114 "${atIdle.line}", the same after M400)`,
  );
}

function marlinSummary(cnc) {
  const lines = cnc.received(0);
  const errors = lines.filter((line) => /^Error:/i.test(line));
  console.log(`cncjs: firmware errors ${errors.length}`);
  for (const line of errors) console.log(`  ${line}`);
  const unknown = lines
    .map((line) => line.match(/^echo:\s*Unknown command:\s*"?([^"]*)"?/i))
    .filter((m) => m)
    .map((m) => m[1]);
  const distinct = [...new Set(unknown)];
  const names = distinct.length ? ` (${distinct.join(', ')})` : '';
  console.log(`cncjs: unknown commands ${unknown.length}${names}`);
  const refusals = lines.filter((line) => /^echo:\s*E\d+/.test(line));
  console.log(`cncjs: refusals ${refusals.length}`);
  for (const line of [...new Set(refusals)]) console.log(`  ${line}`);
}

// What CNCjs's log, the serial traffic, its console, its last states (`describe` writes one
// as a line, when given) and its workflow and sender showed last.
function failureReport(cnc, describe) {
  console.log(`--- the last lines CNCjs logged (all of them in ${cnc.logFile})`);
  for (const line of cnc.log.items) console.log(line);
  console.log('--- the last serial lines (< from the firmware, > from CNCjs, as CNCjs logs them)');
  for (const line of cnc.serial.items) console.log(line);
  console.log("--- the last lines CNCjs's console showed (serialport:read)");
  for (const line of cnc.shown.items) console.log(line);
  if (describe) {
    console.log("--- CNCjs's last controller states (controller:state)");
    for (const { at, state } of cnc.states.slice(-TAIL_LINES)) {
      console.log(`${new Date(at).toISOString()} ${describe(state)}`);
    }
  }
  const sender = cnc.sender || {};
  const { name, total, sent, received, hold, holdReason } = sender;
  console.log(
    `--- workflow ${cnc.workflowHistory.join(' -> ') || '(none)'}; sender ` +
      JSON.stringify({ name, total, sent, received, hold, holdReason }),
  );
}

// Run a driver: parse the command line (`--cncjs`, `--pty`, `--workdir`, `--seconds`,
// `--steps` and the options in `required`), start the CNCjs server, connect to it, and run
// the steps it names, in order, each an `async (cnc) => …` of `steps`, against the port opened
// as `controller`. At the first failure print why and `failureReport` (with `describe`); then,
// whatever happened, `summary(cnc)`, and stop the server. Exits with 0 when every step passed.
function run({ controller, steps, required, summary, describe }) {
  const main = async () => {
    let options;
    try {
      options = parseArgs(process.argv.slice(2), Object.keys(steps), required);
    } catch (err) {
      console.log(`FAILED: arguments: ${err.message}`);
      return 2;
    }
    fs.mkdirSync(options.workdir, { recursive: true });
    const cnc = new Cncjs(options, Date.now() + options.seconds * 1000, controller);
    const stopOnSignal = (signal) => {
      console.log(`FAILED: ${signal} received`);
      cnc.killNow();
      process.exit(1);
    };
    process.on('SIGTERM', () => stopOnSignal('SIGTERM'));
    process.on('SIGINT', () => stopOnSignal('SIGINT'));
    process.on('exit', () => cnc.killNow());
    let step = 'start';
    let status = 0;
    try {
      const port = await cnc.start();
      await cnc.connect();
      console.log(`cncjs: server ok (CNCjs ${cncjsVersion(cnc)} on 127.0.0.1:${port})`);
      for (step of options.steps) {
        await steps[step](cnc);
      }
    } catch (err) {
      console.log(`FAILED: ${step}: ${err instanceof Failed ? err.message : err.stack}`);
      failureReport(cnc, describe);
      status = 1;
    }
    summary(cnc);
    await cnc.stop();
    return status;
  };
  main().then(
    (status) => process.exit(status),
    (err) => {
      console.log(`FAILED: ${err.stack}`);
      process.exit(1);
    },
  );
}

function cncjsVersion(cnc) {
  try {
    return require(path.join(cnc.modules, 'cncjs', 'package.json')).version;
  } catch (_) {
    return '?';
  }
}

module.exports = { Cncjs, Failed, endOfFile, run, workflowEvents };

if (require.main === module) {
  const steps = {
    connect: stepConnect,
    position: stepPosition,
    fault: stepFault,
    job: stepJob,
    finish: stepFinish,
  };
  run({ controller: 'Marlin', steps, required: ['job'], summary: marlinSummary });
}
