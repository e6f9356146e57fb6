"""Stream a G-code file to a controller with Printrun's printcore, as a RepRap host would.

Usage: python stream.py PORT FILE SECONDS

Connects at 115200 baud, waits until printcore is online, prints the file with
printcore.startprint and waits until it has finished (every line answered, the closing
M110 sent and answered). Prints one summary line; exits 1 with a message if that does not
happen within SECONDS.
"""

import sys
import time

from printrun import gcoder
from printrun.printcore import printcore


def fail(message, core):
    print(f"printrun: {message}", flush=True)
    tail = "\n".join(core.log[-20:]) if core is not None else ""
    if tail:
        print(f"printrun: last lines received:\n{tail}", flush=True)
    sys.exit(1)


def main():
    port, path, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    with open(path, encoding="ascii") as f:
        lines = [line.rstrip("\r\n") for line in f]
    deadline = time.time() + seconds
    core = printcore()
    resends = []
    written = []
    core.recvcb = lambda line: resends.append(line) if line.startswith("rs") else None
    core.sendcb = lambda command, gline: written.append(command)
    core.connect(port, 115200)
    while not core.online:
        if time.time() > deadline:
            fail("not online: the controller never answered M105", core)
        time.sleep(0.02)
    job = gcoder.LightGCode(lines)
    if not core.startprint(job):
        fail("startprint refused the job", core)
    # printcore's print thread restarts its send thread as it ends, after `printing` is
    # already false: disconnecting before it ends joins a thread not yet started.
    print_thread = core.print_thread
    while core.printing:
        if time.time() > deadline:
            fail(f"the job did not finish: line {core.queueindex} of {len(job)}", core)
        time.sleep(0.02)
    # The closing `M110 N-1` is answered too before the port is released.
    while not core.clear:
        if time.time() > deadline:
            fail("the closing M110 was not answered", core)
        time.sleep(0.02)
    print_thread.join(max(deadline - time.time(), 0.0))
    if print_thread.is_alive():
        fail("printcore's print thread did not end", core)
    sent = len([c for c in written if "M105" not in c and "M110" not in c])
    core.disconnect()
    print(f"printrun: done, {sent} lines written, {len(resends)} resend requests", flush=True)


if __name__ == "__main__":
    main()
