"""Drive a printer with OctoPrint's own server, as a person does through its web interface.

Usage: python drive.py --pty PTY --job FILE --basedir DIR [--seconds N] [--steps LIST]
                       [--set KEY=YAML ...]

Runs `octoprint serve` (the package installed beside this Python) on a free port of
127.0.0.1 with a fresh base directory DIR. The `config.yaml` written there before the start
answers what a fresh install asks a person (first-run wizard, one admin user with an API key)
and turns off the bundled plugins that reach the network or the local network (update checks,
announcements, usage tracking, plugin repository, health checks, zeroconf discovery). Every
serial setting keeps OctoPrint's default except two: `serial.additionalPorts` names PTY so
that OctoPrint lists it (it scans /dev/tty* only), and `serial.log` is on so that
DIR/logs/serial.log records every line exchanged with the printer.

Then, through OctoPrint's REST API, the steps (all by default, in this order):

  connect       connect to PTY at 115200 baud, wait for Operational, check it stays so
  temperatures  set the hot end to 200 C and the bed to 60 C; /api/printer shows both the
                actual and the target temperatures while they heat
  print         upload FILE to local storage, print it, wait until it is done (100 %)
  pause         print it again: pause at 10 %, check that it holds, resume, cancel
  sd            upload FILE to the printer's SD card (M28/M29), list the card (M20), select
                and print it from the card (M23/M24), follow its progress (M27) to the end

Prints `octoprint: <step> ok` or `octoprint: <step> FAILED: <why>` per step and exits 1 at
the first failure, after the tails of DIR/logs/serial.log and DIR/logs/octoprint.log. At the
end, whatever happened, prints from the serial log `octoprint: firmware errors N` with every
error line the printer sent (`Error:` or `!!`), `octoprint: resend requests N` with the
first of them, and `octoprint: unknown commands N` with the commands the printer said it
does not know (OctoPrint passes over those). OctoPrint is stopped before the program exits,
by SIGTERM, then SIGKILL; it is also killed by the kernel if this program dies first.
"""

import argparse
import ctypes
import os
import re
import signal
import socket
import subprocess
import sys
import time
import traceback

import requests
import yaml

USER = "forja"
PASSWORD = "forja-acceptance"
API_KEY = "FORJAOCTOPRINTACCEPTANCE0123456789"

STEPS = ["connect", "temperatures", "print", "pause", "sd"]

# Bundled plugins that contact hosts other than this one when they run.
NETWORK_PLUGINS = [
    "announcements",
    "backup",
    "discovery",
    "errortracking",
    "health_check",
    "pluginmanager",
    "softwareupdate",
    "tracking",
]


class Failed(Exception):
    """A step did not do what it should: the message says what was seen."""


class OctoPrint:
    """A running `octoprint serve` and its REST API."""

    def __init__(self, basedir, deadline):
        self.basedir = basedir
        self.deadline = deadline
        self.process = None
        self.url = None
        self.session = requests.Session()
        self.session.headers["X-Api-Key"] = API_KEY

    # ---- set-up -------------------------------------------------------------------------

    def configure(self, pty, overrides):
        os.makedirs(self.basedir, exist_ok=True)
        config = {
            "server": {
                "firstRun": False,
                "onlineCheck": {"enabled": False},
                "pluginBlacklist": {"enabled": False},
                "pythonEolCheck": {"enabled": False},
            },
            "plugins": {"_disabled": NETWORK_PLUGINS},
            "serial": {"additionalPorts": [pty], "log": True},
        }
        for path, value in overrides:
            node = config
            *parents, leaf = path.split(".")
            for key in parents:
                node = node.setdefault(key, {})
            node[leaf] = value
        with open(os.path.join(self.basedir, "config.yaml"), "w", encoding="utf-8") as f:
            yaml.safe_dump(config, f)
        octoprint = os.path.join(os.path.dirname(sys.executable), "octoprint")
        made = subprocess.run(
            [octoprint, "--basedir", self.basedir, "user", "add", USER,
             "--password", PASSWORD, "--admin"],
            capture_output=True, text=True, timeout=120, check=False,
        )
        if made.returncode != 0 or "User created" not in made.stdout:
            raise Failed(f"`octoprint user add` failed: {made.stdout}{made.stderr}")
        # OctoPrint's user file keeps each user's API key; the CLI has no option for one.
        users_file = os.path.join(self.basedir, "users.yaml")
        with open(users_file, encoding="utf-8") as f:
            users = yaml.safe_load(f)
        users[USER]["apikey"] = API_KEY
        with open(users_file, "w", encoding="utf-8") as f:
            yaml.safe_dump(users, f)

    def start(self):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{port}"
        octoprint = os.path.join(os.path.dirname(sys.executable), "octoprint")
        command = [octoprint, "serve", "--basedir", self.basedir, "--host", "127.0.0.1",
                   "--port", str(port)]
        if os.geteuid() == 0:
            # OctoPrint refuses root unless told; containers and CI run tests as root.
            command.append("--iknowwhatimdoing")
        out = open(os.path.join(self.basedir, "serve.out"), "w", encoding="utf-8")
        self.process = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
            preexec_fn=die_with_parent,
        )
        out.close()
        end = min(time.time() + 120, self.deadline)
        while True:
            if self.process.poll() is not None:
                raise Failed(f"octoprint serve exited with {self.process.returncode}:\n"
                             + tail(os.path.join(self.basedir, "serve.out"), 30))
            try:
                r = self.session.get(self.url + "/api/version", timeout=2)
                if r.status_code == 200:
                    return r.json()
                if r.status_code in (401, 403):
                    raise Failed(f"the API key is refused: {r.status_code} {r.text}")
            except requests.ConnectionError:
                pass
            if time.time() > end:
                raise Failed("the server did not answer /api/version within 120 s")
            time.sleep(0.5)

    def stop(self):
        if self.process is None or self.process.poll() is not None:
            return
        try:
            self.post("/api/connection", {"command": "disconnect"}, ok=(204,), timeout=5)
        except Exception:  # the server may be the thing that failed
            pass
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    # ---- the REST API -------------------------------------------------------------------

    def get(self, path, **params):
        r = self.session.get(self.url + path, params=params, timeout=30)
        if r.status_code != 200:
            raise Failed(f"GET {path}: {r.status_code} {r.text.strip()}")
        return r.json()

    def post(self, path, body=None, ok=(200, 201, 204), timeout=30, **kwargs):
        if body is not None:
            kwargs["json"] = body
        r = self.session.post(self.url + path, timeout=timeout, **kwargs)
        if r.status_code not in ok:
            raise Failed(f"POST {path} {body or ''}: {r.status_code} {r.text.strip()}")
        return r.json() if r.content else None

    def printer(self, connecting=False):
        """GET /api/printer; a printer in an error state fails the step.

        With `connecting`, None while OctoPrint opens the port and greets the printer."""
        r = self.session.get(self.url + "/api/printer", timeout=30)
        if r.status_code == 409:
            state = self.connection_state()
            if connecting and not (state.startswith("Error") or state.endswith("after error")
                                   or state == "Closed"):
                return None
            raise Failed(f"the printer is not operational ({self.connection_state()}): "
                         + last_error(self))
        if r.status_code != 200:
            raise Failed(f"GET /api/printer: {r.status_code} {r.text.strip()}")
        p = r.json()
        flags = p["state"]["flags"]
        if flags.get("error") or flags.get("closedOrError"):
            raise Failed(f"the printer is in error: {p['state']['text']} "
                         f"({p['state'].get('error') or self.connection_state()})")
        return p

    def connection_state(self):
        """The connection state's text, e.g. `Operational`, `Printing`, `Closed`."""
        c = self.get("/api/connection")["current"]
        return c["state"]

    def job(self):
        return self.get("/api/job")

    def wait(self, what, seconds, condition, interval=0.25):
        """Poll `condition()` until it returns a true value (returned); fail after `seconds`."""
        end = min(time.time() + seconds, self.deadline)
        while True:
            value = condition()
            if value:
                return value
            if time.time() > end:
                raise Failed(f"{what}: not within {seconds:.0f} s ({self.state_text()})")
            time.sleep(interval)

    def state_text(self):
        """The printer's state as OctoPrint shows it, e.g. `Sending file to SD`."""
        r = self.session.get(self.url + "/api/printer", timeout=30)
        if r.status_code == 200:
            state = r.json()["state"]
            flags = ", ".join(name for name, on in state["flags"].items() if on)
            return f"printer state {state['text']!r}, flags {flags or 'none'}"
        return f"connection state {self.connection_state()!r}"


def die_with_parent():
    """In the child before exec: the kernel kills it when the program that started it dies."""
    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGKILL)


def tail(path, count):
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.readlines()
    except OSError as e:
        return f"({path}: {e})"
    return "".join(lines[-count:])


NOT_CONNECTED = {"state": {"text": "Connecting", "flags": {"ready": False}}}


def operational(p):
    return p["state"]["text"] == "Operational" and p["state"]["flags"]["ready"]


# ---- the steps --------------------------------------------------------------------------


def step_connect(op, pty):
    ports = op.get("/api/connection")["options"]["ports"]
    if pty not in ports:
        raise Failed(f"OctoPrint does not list {pty}: it lists {ports}")
    op.post("/api/connection", {"command": "connect", "port": pty, "baudrate": 115200})
    op.wait("the printer becomes Operational", 60,
            lambda: operational(op.printer(connecting=True) or NOT_CONNECTED))
    # Idle, OctoPrint asks M105 every 2 s: four rounds of it.
    end = time.time() + 8
    while time.time() < end:
        p = op.printer()
        if not operational(p):
            raise Failed(f"the printer left Operational: {p['state']['text']}")
        time.sleep(0.5)
    firmware = [line for line in serial_lines(op) if "FIRMWARE_NAME" in line]
    return f"firmware {firmware[-1].split('FIRMWARE_NAME:')[1].split()[0]}" if firmware else ""


def step_temperatures(op):
    start = op.printer()["temperature"]
    t0, b0 = start["tool0"]["actual"], start["bed"]["actual"]
    op.post("/api/printer/tool", {"command": "target", "targets": {"tool0": 200}})
    op.post("/api/printer/bed", {"command": "target", "target": 60})

    def heating():
        t = op.printer()["temperature"]
        tool, bed = t["tool0"], t["bed"]
        if (tool["target"] == 200 and bed["target"] == 60
                and tool["actual"] >= t0 + 5 and bed["actual"] >= b0 + 1):
            return tool, bed
        return None

    tool, bed = op.wait("the hot end and the bed heat towards their targets", 60, heating)
    return (f"hot end {t0:.1f} -> {tool['actual']:.1f}/{tool['target']:.0f} C, "
            f"bed {b0:.1f} -> {bed['actual']:.1f}/{bed['target']:.0f} C")


def upload(op, origin, job):
    name = os.path.basename(job)
    with open(job, "rb") as f:
        body = op.post(f"/api/files/{origin}",
                       files={"file": (name, f, "application/octet-stream")},
                       data={"select": "false", "print": "false"}, timeout=60)
    return body


def job_events(op, kind, origin, path):
    """How many times octoprint.log says `Print job <kind>` for `path` on `origin`."""
    try:
        with open(os.path.join(op.basedir, "logs", "octoprint.log"), encoding="utf-8",
                  errors="replace") as f:
            text = f.read()
    except OSError:
        return 0
    return text.count(f"Print job {kind} - origin: {origin}, path: {path},")


def start_print(op, origin, path, seconds=30):
    """Select `path` on `origin` and print it; return once OctoPrint says the print started."""
    started = job_events(op, "started", origin, path)
    done = job_events(op, "done", origin, path)
    op.post(f"/api/files/{origin}/{path}", {"command": "select", "print": True})
    op.wait(f"the print of {path} starts", seconds,
            lambda: op.printer() and job_events(op, "started", origin, path) > started)
    return done


def wait_done(op, origin, path, done_before, seconds):
    """Until the print of `path` is done, at 100 %, and the printer Operational again."""

    def done():
        p = op.printer()
        if not p["state"]["flags"]["printing"] and not p["state"]["flags"]["paused"] \
                and job_events(op, "cancelled", origin, path) > cancelled:
            raise Failed(f"the print of {path} was cancelled: {p['state']['text']}")
        return operational(p) and job_events(op, "done", origin, path) > done_before

    cancelled = job_events(op, "cancelled", origin, path)
    op.wait(f"the print of {path} ends", seconds, done, interval=0.5)
    j = op.job()
    completion = j["progress"]["completion"]
    if completion is None or completion < 100:
        raise Failed(f"the print of {path} is done at {completion} %")
    return j


def step_print(op, job):
    name = os.path.basename(job)
    stored = upload(op, "local", job)
    if not stored or not stored.get("done"):
        raise Failed(f"the upload is not done: {stored}")
    done = start_print(op, "local", name)
    j = wait_done(op, "local", name, done, 240)
    return f"{j['progress']['printTime']} s of printing"


def step_pause(op, job):
    name = os.path.basename(job)
    start_print(op, "local", name)

    def along():
        p = op.printer()
        if not p["state"]["flags"]["printing"]:
            raise Failed(f"the print ended before it could be paused: {p['state']['text']}")
        j = op.job()
        return j if (j["progress"]["completion"] or 0) >= 10 else None

    op.wait("the print reaches 10 %", 120, along)
    op.post("/api/job", {"command": "pause", "action": "pause"})
    op.wait("the print pauses", 30, lambda: op.printer()["state"]["flags"]["paused"])
    held = op.job()["progress"]["filepos"]
    time.sleep(3)
    p, moved = op.printer(), op.job()["progress"]["filepos"]
    if not p["state"]["flags"]["paused"] or moved != held:
        raise Failed(f"the pause does not hold: {p['state']['text']}, "
                     f"file position {held} -> {moved}")
    op.post("/api/job", {"command": "pause", "action": "resume"})

    def resumed():
        p = op.printer()
        flags = p["state"]["flags"]
        return flags["printing"] and not flags["paused"] and op.job()["progress"]["filepos"] > held

    op.wait("the print resumes", 30, resumed)
    cancelled = job_events(op, "cancelled", "local", name)
    op.post("/api/job", {"command": "cancel"})
    op.wait("the print is cancelled", 60,
            lambda: operational(op.printer())
            and job_events(op, "cancelled", "local", name) > cancelled)
    if job_events(op, "done", "local", name) > 1:
        raise Failed("the cancelled print ran to the end")
    return f"paused at byte {held}, resumed, cancelled"


def step_sd(op, job):
    sd = op.get("/api/printer/sd")
    if not sd.get("ready"):
        raise Failed("OctoPrint has no SD card: the printer did not report one after M21 "
                     + sent_and_received(op, "M21"))
    stored = upload(op, "sdcard", job)
    remote = (stored or {}).get("files", {}).get("sdcard", {}).get("name")
    if not remote:
        raise Failed(f"the SD upload answered {stored}")
    # The upload answers the name OctoPrint sent with M28 (`/job.gco`); the card's list and
    # its print commands name files without the leading slash.
    remote = remote.lstrip("/")

    def streamed():
        p = op.printer()
        return operational(p) and not p["state"]["flags"].get("printing")

    # OctoPrint streams the file with M28 <name>, the lines, M29, then lists the card (M20).
    op.wait("the transfer to the SD card ends", 60, streamed, interval=0.5)
    files = op.get("/api/files/sdcard", force="true")["files"]
    names = [f["name"] for f in files]
    # A card with long names lists the file by its 8.3 name and shows the long one.
    listed = [f["name"] for f in files
              if remote.lower() in (f["name"].lower(), str(f.get("display")).lower())]
    if not listed:
        raise Failed(f"the SD card does not list {remote}: M20 listed {names} "
                     + sent_and_received(op, "M20"))
    remote = listed[0]
    print(f"octoprint: sd-upload ok ({remote}, the card lists {names})", flush=True)
    reports_before = len(sd_progress(op))
    done = start_print(op, "sdcard", remote)
    wait_done(op, "sdcard", remote, done, 240)
    reports = sd_progress(op)[reports_before:]
    if not reports:
        raise Failed("the printer printed from the card but never reported its progress "
                     "(`SD printing byte N/M`) " + sent_and_received(op, "M27"))
    return f"printed from the card, progress reported {len(reports)} times, last {reports[-1]}"


def sd_progress(op):
    """The `SD printing byte N/M` reports in the serial log (M27, or its autoreport)."""
    return [line.split("Recv: ", 1)[1] for line in serial_lines(op)
            if "Recv: SD printing byte" in line]


# ---- the logs ---------------------------------------------------------------------------


def serial_lines(op):
    try:
        with open(os.path.join(op.basedir, "logs", "serial.log"), encoding="utf-8",
                  errors="replace") as f:
            return f.read().splitlines()
    except OSError:
        return []


def last_error(op):
    """What made OctoPrint leave Operational last: the lines before its state change."""
    lines = serial_lines(op)
    at = [i for i, line in enumerate(lines) if re.search(r'to "(Error|Offline|Closed)', line)]
    if not at:
        return "(the serial log shows no state change to Error or Offline)"
    return "\n" + "\n".join(lines[max(0, at[0] - 4):at[0] + 1])


def sent_and_received(op, command):
    """The serial log around the last time `command` was sent."""
    lines = serial_lines(op)
    at = [i for i, line in enumerate(lines) if re.search(rf"Send: (N\d+ )?{command}\b", line)]
    if not at:
        return f"(OctoPrint never sent {command})"
    return "\n" + "\n".join(lines[at[-1]:at[-1] + 6])


ERROR = re.compile(r"Recv: (Error:|!!)", re.IGNORECASE)
RESEND = re.compile(r"Recv: (Resend|rs)\b", re.IGNORECASE)
UNKNOWN = re.compile(r"Recv: .*unknown command", re.IGNORECASE)


def report_errors(op):
    lines = serial_lines(op)
    errors = [line for line in lines if ERROR.search(line)]
    resends = [line for line in lines if RESEND.search(line)]
    print(f"octoprint: firmware errors {len(errors)}", flush=True)
    for line in errors:
        print(f"octoprint:   {line}", flush=True)
    print(f"octoprint: resend requests {len(resends)}", flush=True)
    for line in resends[:20]:
        print(f"octoprint:   {line}", flush=True)
    # OctoPrint passes over these; they name what the firmware lacks.
    unknown = sorted({line.split("Recv: ", 1)[1] for line in lines if UNKNOWN.search(line)})
    print(f"octoprint: unknown commands {len(unknown)}", flush=True)
    for line in unknown:
        print(f"octoprint:   {line}", flush=True)


def report_logs(op):
    print("octoprint: --- last 40 lines of serial.log", flush=True)
    print(tail(os.path.join(op.basedir, "logs", "serial.log"), 40), end="", flush=True)
    log = os.path.join(op.basedir, "logs", "octoprint.log")
    try:
        with open(log, encoding="utf-8", errors="replace") as f:
            notable = [line for line in f if " - WARNING - " in line or " - ERROR - " in line
                       or "Changing monitoring state" in line or "firmware" in line.lower()]
    except OSError:
        notable = []
    print("octoprint: --- octoprint.log: state changes, warnings and errors (last 30)",
          flush=True)
    print("".join(notable[-30:]), end="", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pty", required=True)
    parser.add_argument("--job", required=True)
    parser.add_argument("--basedir", required=True)
    parser.add_argument("--seconds", type=float, default=300)
    parser.add_argument("--steps", default=",".join(STEPS))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=YAML",
                        help="for diagnosis only: one more config.yaml setting, e.g. "
                             "serial.ignoreErrorsFromFirmware=true (the test sets none)")
    args = parser.parse_args()
    overrides = []
    for item in args.set:
        key, _, value = item.partition("=")
        overrides.append((key, yaml.safe_load(value)))
    steps = args.steps.split(",")
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        parser.error(f"unknown steps {unknown}: the steps are {STEPS}")
    # A SIGTERM (the test's time limit) fails the step under way; OctoPrint is then stopped.
    def on_sigterm(*_):
        raise Failed("stopped by SIGTERM (the time limit)")

    signal.signal(signal.SIGTERM, on_sigterm)

    op = OctoPrint(os.path.abspath(args.basedir), time.time() + args.seconds)
    actions = {
        "connect": lambda: step_connect(op, args.pty),
        "temperatures": lambda: step_temperatures(op),
        "print": lambda: step_print(op, args.job),
        "pause": lambda: step_pause(op, args.job),
        "sd": lambda: step_sd(op, args.job),
    }
    failed = False
    try:
        for name, action in [("setup", lambda: op.configure(args.pty, overrides)),
                             ("server", lambda: f"version {op.start()['server']}")] + \
                [(s, actions[s]) for s in steps]:
            began = time.time()
            try:
                detail = action()
            except Failed as e:
                print(f"octoprint: {name} FAILED: {e}", flush=True)
                failed = True
                break
            except requests.RequestException as e:
                print(f"octoprint: {name} FAILED: the server did not answer: {e}", flush=True)
                failed = True
                break
            except Exception as e:  # an answer of a shape the step did not expect
                print(f"octoprint: {name} FAILED: {type(e).__name__}: {e}", flush=True)
                traceback.print_exc(file=sys.stdout)
                failed = True
                break
            spent = f"{time.time() - began:.1f} s"
            print(f"octoprint: {name} ok ({detail + ', ' if detail else ''}{spent})",
                  flush=True)
    finally:
        op.stop()
        if op.url is not None:
            report_errors(op)
        if failed:
            report_logs(op)
    if failed:
        sys.exit(1)
    print("octoprint: done", flush=True)


if __name__ == "__main__":
    main()
