//! A QEMU end-to-end harness for the STM32F4 firmware.
//!
//! [`QemuBoard::boot`] starts `qemu-system-arm -machine netduinoplus2` with the firmware
//! image, connects to the host UART (the machine's sixth serial port, USART6, on a local TCP
//! port) and waits for the firmware's `start` line. A test then [`send`](QemuBoard::send)s
//! bytes and [`read_line`](QemuBoard::read_line)s replies, and can read the firmware's memory
//! by symbol through QEMU's machine protocol (QMP) without stopping it
//! ([`read_symbol_words`](QemuBoard::read_symbol_words)). Dropping the board ends QEMU.
//!
//! QEMU waits for the link's client before it starts the CPU, so no byte the firmware sends is
//! lost; bytes a host sends before `start` would be (the UART is not enabled yet), which is why
//! `boot` waits for it. The firmware resets on a panic or a fault, and QEMU runs with
//! `-no-reboot`, so such a reset ends QEMU: [`QemuBoard::is_running`] tells.
//!
//! The G-code job goes through the `forja` client's own code
//! ([`forja_host::client::send_program`]: its `M115` probe, its handshake, its streamer and
//! window) over [`QemuBoard::stream`]; the rest of the harness uses the standard library and
//! the `object` crate.

use std::fmt;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use forja_host::client::{Observer, SendReport, send_program};
use forja_host::link::{Connection, Link};
use forja_host::program::Program;
use forja_host::streamer::Config;
use object::{Object, ObjectSymbol};

/// The QEMU binary.
pub const QEMU: &str = "qemu-system-arm";

/// The QEMU machine of the `qemu` pin map.
pub const MACHINE: &str = "netduinoplus2";

/// The serial port (0-based) wired to the host UART: USART6.
pub const LINK_SERIAL_INDEX: usize = 5;

/// How long [`QemuBoard::boot`] waits for QEMU and for `start`.
pub const BOOT_TIMEOUT: Duration = Duration::from_secs(20);

/// A harness error, with what was being done.
#[derive(Debug)]
pub struct Error(String);

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Error {}

impl From<Error> for String {
    fn from(e: Error) -> String {
        e.0
    }
}

fn err(what: impl fmt::Display, e: impl fmt::Display) -> Error {
    Error(format!("{what}: {e}"))
}

/// Whether `qemu-system-arm` can be started.
pub fn qemu_available() -> bool {
    Command::new(QEMU)
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// A free TCP port on the loopback interface (free when asked; QEMU binds it right after).
pub fn free_port() -> Result<u16, Error> {
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).map_err(|e| err("free port", e))?;
    listener
        .local_addr()
        .map(|a| a.port())
        .map_err(|e| err("free port", e))
}

/// The QEMU command line that runs `elf` with the host link on `127.0.0.1:link_port`.
/// With `wait`, QEMU waits for the link's client before starting the CPU. With `qmp_port`,
/// the machine protocol listens there too.
pub fn command(elf: &Path, link_port: u16, wait: bool, qmp_port: Option<u16>) -> Command {
    let mut cmd = Command::new(QEMU);
    cmd.args(["-machine", MACHINE, "-display", "none", "-monitor", "none"])
        .arg("-no-reboot")
        .arg("-kernel")
        .arg(elf);
    for _ in 0..LINK_SERIAL_INDEX {
        cmd.args(["-serial", "null"]);
    }
    let wait = if wait { "on" } else { "off" };
    cmd.arg("-serial")
        .arg(format!("tcp:127.0.0.1:{link_port},server=on,wait={wait}"));
    if let Some(port) = qmp_port {
        cmd.arg("-qmp")
            .arg(format!("tcp:127.0.0.1:{port},server=on,wait=off"));
    }
    cmd
}

/// Connect to `127.0.0.1:port`, retrying while QEMU starts.
fn connect(port: u16, child: &mut Child, deadline: Instant) -> Result<TcpStream, Error> {
    loop {
        match TcpStream::connect((Ipv4Addr::LOCALHOST, port)) {
            Ok(stream) => return Ok(stream),
            Err(e) => {
                if let Ok(Some(status)) = child.try_wait() {
                    return Err(err("QEMU exited before listening", status));
                }
                if Instant::now() > deadline {
                    return Err(err(format!("connect to 127.0.0.1:{port}"), e));
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
}

/// The address of `symbol` in `elf`.
pub fn symbol_address(elf: &Path, symbol: &str) -> Result<u64, Error> {
    let data = std::fs::read(elf).map_err(|e| err(elf.display(), e))?;
    let file = object::File::parse(&*data).map_err(|e| err(elf.display(), e))?;
    file.symbols()
        .find(|s| s.name() == Ok(symbol))
        .map(|s| s.address())
        .ok_or_else(|| Error(format!("{}: no symbol {symbol}", elf.display())))
}

/// A firmware image running in QEMU, with its host link connected.
pub struct QemuBoard {
    child: Child,
    elf: PathBuf,
    link: BufReader<TcpStream>,
    qmp: Option<BufReader<TcpStream>>,
    qmp_port: u16,
    link_port: u16,
}

impl QemuBoard {
    /// Start QEMU with `elf`, connect the host link and wait for the `start` line.
    pub fn boot(elf: &Path) -> Result<Self, Error> {
        if !qemu_available() {
            return Err(Error(format!(
                "{QEMU} not found: install it (Debian/Ubuntu: apt-get install qemu-system-arm)"
            )));
        }
        let link_port = free_port()?;
        let qmp_port = free_port()?;
        let mut child = command(elf, link_port, true, Some(qmp_port))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| err(format!("start {QEMU}"), e))?;
        let deadline = Instant::now() + BOOT_TIMEOUT;
        let link = match connect(link_port, &mut child, deadline) {
            Ok(link) => link,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(e);
            }
        };
        let mut board = Self {
            child,
            elf: elf.to_path_buf(),
            link: BufReader::new(link),
            qmp: None,
            qmp_port,
            link_port,
        };
        let first = board.read_line(BOOT_TIMEOUT)?;
        if first != "start" {
            return Err(Error(format!("expected `start` at boot, got {first:?}")));
        }
        Ok(board)
    }

    /// The TCP port of the host link.
    pub fn link_port(&self) -> u16 {
        self.link_port
    }

    /// Send bytes on the host link.
    pub fn send(&mut self, bytes: &[u8]) -> Result<(), Error> {
        let link = self.link.get_mut();
        link.write_all(bytes)
            .and_then(|()| link.flush())
            .map_err(|e| err("send on the host link", e))
    }

    /// The next line from the host link, without its terminator; fails after `timeout`.
    pub fn read_line(&mut self, timeout: Duration) -> Result<String, Error> {
        self.link
            .get_ref()
            .set_read_timeout(Some(timeout))
            .map_err(|e| err("host link", e))?;
        let mut line = Vec::new();
        match self.link.read_until(b'\n', &mut line) {
            Ok(0) => Err(Error("host link closed (QEMU ended?)".into())),
            Ok(_) if line.ends_with(b"\n") => {
                while line.last().is_some_and(|b| *b == b'\n' || *b == b'\r') {
                    line.pop();
                }
                Ok(String::from_utf8_lossy(&line).into_owned())
            }
            Ok(_) => Err(Error("host link closed in the middle of a line".into())),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                Err(Error(format!(
                    "no line from the firmware within {timeout:?} (partial: {:?})",
                    String::from_utf8_lossy(&line)
                )))
            }
            Err(e) => Err(err("read the host link", e)),
        }
    }

    /// `count` 32-bit words of guest memory at the address of `symbol` in the image.
    pub fn read_symbol_words(&mut self, symbol: &str, count: usize) -> Result<Vec<u32>, Error> {
        let address = symbol_address(&self.elf, symbol)?;
        self.read_words(address, count)
    }

    /// `count` 32-bit words of guest memory at `address`, read through QMP while the CPU runs.
    pub fn read_words(&mut self, address: u64, count: usize) -> Result<Vec<u32>, Error> {
        let reply = self.qmp_command(&format!(
            r#"{{"execute":"human-monitor-command","arguments":{{"command-line":"xp /{count}wx {address:#x}"}}}}"#
        ))?;
        // `"return": "0000000020000000: 0x0000001c 0x00000002\r\n…"`
        let text = reply
            .split_once(r#""return""#)
            .map(|(_, r)| r)
            .ok_or_else(|| Error(format!("QMP: unexpected reply {reply}")))?;
        let words: Vec<u32> = text
            .split(|c: char| c.is_whitespace() || c == '"' || c == '\\')
            .filter_map(|t| t.strip_prefix("0x"))
            .filter_map(|t| u32::from_str_radix(t, 16).ok())
            .collect();
        if words.len() != count {
            return Err(Error(format!("QMP: expected {count} words in {reply}")));
        }
        Ok(words)
    }

    /// Send one QMP command and return its reply line (events are skipped).
    fn qmp_command(&mut self, json: &str) -> Result<String, Error> {
        if self.qmp.is_none() {
            let deadline = Instant::now() + BOOT_TIMEOUT;
            let stream = connect(self.qmp_port, &mut self.child, deadline)?;
            stream
                .set_read_timeout(Some(BOOT_TIMEOUT))
                .map_err(|e| err("QMP", e))?;
            let mut qmp = BufReader::new(stream);
            let mut greeting = String::new();
            qmp.read_line(&mut greeting)
                .map_err(|e| err("QMP greeting", e))?;
            self.qmp = Some(qmp);
            self.qmp_command(r#"{"execute":"qmp_capabilities"}"#)?;
        }
        let qmp = self
            .qmp
            .as_mut()
            .ok_or_else(|| Error("QMP not connected".into()))?;
        qmp.get_mut()
            .write_all(format!("{json}\n").as_bytes())
            .map_err(|e| err("QMP send", e))?;
        loop {
            let mut line = String::new();
            if qmp.read_line(&mut line).map_err(|e| err("QMP read", e))? == 0 {
                return Err(Error("QMP closed (QEMU ended?)".into()));
            }
            if line.contains(r#""return""#) {
                return Ok(line);
            }
            if line.contains(r#""error""#) {
                return Err(Error(format!("QMP: {}", line.trim())));
            }
        }
    }

    /// Whether QEMU still runs (a firmware reset ends it).
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
}

impl Drop for QemuBoard {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The job of the end-to-end test, streamed as numbered, checksummed G-code lines: short real
/// moves on X, Y, Z and A (rapid, feed, relative, an arc), in machine coordinates from the
/// power-on position. Coordinates are whole steps of the default machine (1/80 mm on X, Y
/// and A, 1/400 mm on Z), so that every report is exact.
pub const JOB: &[&str] = &[
    "G21",
    "G90",
    "G94",
    "G0 X2 Y1",
    "G1 X4 Y2 F2400",
    "G1 Z0.5 F600",
    "G1 X6 Y2.5 F3000",
    "G1 X6 Y5",
    "G1 X8.75 Y5 Z1",
    "G0 Z2",
    "G0 X10 Y6.25",
    "G1 Z1.5 F600",
    "G2 X12 Y8.25 I2 J0 F1800",
    "G1 X12 Y10",
    "G3 X10 Y12 I-2 J0",
    "G1 X7.5 Y12",
    "G91",
    "G1 X-1.25 Y-0.5 Z0.25",
    "G1 X2.5",
    "G1 Y1.25 Z-0.5",
    "G0 A15",
    "G1 X-0.5 Y-0.25 A-5 F1500",
    "G90",
    "G1 X5 Y10 Z1.25 F3000",
    "G1 X3.75 Y8",
    "G0 Z3",
    "G0 X1.25 Y1.25",
    "G1 Z2.5 F600",
    "G1 X2.5 Y2.5 F2400",
    "G0 Z4",
];

/// The number of the line of [`JOB`] (1-based, as the streamer numbers them) whose first copy
/// is sent with a damaged check: the firmware must ask for it again (`rs`), and take it when
/// resent.
pub const CORRUPTED: u32 = 10;

/// The program of the end-to-end test, uploaded with frames 03 and run with frame 02 `Start`.
pub const PROGRAM: &[&str] = &[
    "G90",
    "G0 X5 Y5",
    "G1 Z1 F600",
    "G1 X10 Y5 F2400",
    "G1 X10 Y7.5",
    "G2 X12.5 Y10 I2.5 J0",
    "G91",
    "G1 X-2.5 Y-1.25 Z0.5",
    "G90",
    "G0 A20",
    "G0 Z3.75",
];

/// The axes the firmware reports, in order.
const AXES: [char; 4] = ['X', 'Y', 'Z', 'A'];

/// How long one line or frame may wait for its answer.
const REPLY_TIMEOUT: Duration = Duration::from_secs(20);

/// How long the machine may take to finish the job, or the program.
const MOTION_TIMEOUT: Duration = Duration::from_secs(60);

/// `bytes` with the check of the numbered line `number` in them damaged, if they hold that line:
/// the last digit after its `*` changed to its neighbour (`0` and `1`, `2` and `3`, …), which
/// keeps the check in range (at most 255 for the XOR, 65535 for the CRC-16) and wrong.
fn damage_check(bytes: &[u8], number: u32) -> Option<Vec<u8>> {
    let head = format!("N{number} ");
    let start = (0..bytes.len()).find(|&i| {
        (i == 0 || bytes.get(i - 1) == Some(&b'\n'))
            && bytes
                .get(i..)
                .is_some_and(|rest| rest.starts_with(head.as_bytes()))
    })?;
    let line = bytes.get(start..)?;
    let len = line.iter().position(|&b| b == b'\r' || b == b'\n')?;
    let line = line.get(..len)?;
    let star = line.iter().rposition(|&b| b == b'*')?;
    let last = start + len - 1;
    if star + 1 == len || !bytes.get(last)?.is_ascii_digit() {
        return None;
    }
    let mut out = bytes.to_vec();
    *out.get_mut(last)? ^= 1;
    Some(out)
}

/// The board's host link as the client's byte link ([`Link`]), damaging the check of the first
/// copy of line `damage` it writes.
struct ClientLink {
    stream: TcpStream,
    /// Bytes the board had already read from the link and not returned.
    buffered: Vec<u8>,
    /// The line still to damage.
    damage: Option<u32>,
}

impl Link for ClientLink {
    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        if let Some(number) = self.damage
            && let Some(damaged) = damage_check(bytes, number)
        {
            self.damage = None;
            return self.stream.write_all(&damaged);
        }
        self.stream.write_all(bytes)
    }

    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if !self.buffered.is_empty() {
            let n = buf.len().min(self.buffered.len());
            buf[..n].copy_from_slice(&self.buffered[..n]);
            self.buffered.drain(..n);
            return Ok(n);
        }
        self.stream
            .set_read_timeout(Some(timeout.max(Duration::from_millis(1))))?;
        match self.stream.read(buf) {
            Ok(0) => Err(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "the host link closed (QEMU ended?)",
            )),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                Ok(0)
            }
            read => read,
        }
    }
}

/// What the client told about the job as it went.
#[derive(Default)]
struct Notices(Vec<String>);

impl Observer for Notices {
    fn notice(&mut self, text: &str) {
        self.0.push(text.to_string());
    }
}

/// Positions read from `M114` or frame 51, in [`AXES`] order, mm.
type Position = [f64; 4];

/// The positions of an `X:… Y:… Z:… A:… Count …` reply (the counts are not read).
fn parse_m114(reply: &str) -> Result<Position, Error> {
    let mut out = [f64::NAN; 4];
    let positions = reply.split(" Count").next().unwrap_or(reply);
    for word in positions.split_whitespace() {
        if let Some((letter, value)) = word.split_once(':')
            && let Some(i) = AXES.iter().position(|a| a.to_string() == letter)
        {
            out[i] = value
                .parse()
                .map_err(|_| Error(format!("M114: bad value in {reply:?}")))?;
        }
    }
    if out.iter().any(|v| v.is_nan()) {
        return Err(Error(format!("M114: not every axis in {reply:?}")));
    }
    Ok(out)
}

/// The positions of frame 51.
fn parse_positions(frame: &str) -> Result<Position, Error> {
    use forja_protocol::frame::ControllerMessage;
    match ControllerMessage::decode(frame.as_bytes()) {
        Ok(ControllerMessage::Positions(p)) => {
            let mut out = [0.0; 4];
            for (i, letter) in AXES.iter().enumerate() {
                let tenths = p
                    .get(*letter as u8)
                    .ok_or_else(|| Error(format!("51 without axis {letter}: {frame}")))?;
                out[i] = f64::from(tenths) / 10_000.0;
            }
            Ok(out)
        }
        other => Err(Error(format!(
            "expected frame 51, got {frame:?} ({other:?})"
        ))),
    }
}

fn show(p: &Position) -> String {
    AXES.iter()
        .zip(p)
        .map(|(a, v)| format!("{a} {v:.4}"))
        .collect::<Vec<_>>()
        .join(" ")
}

impl QemuBoard {
    /// The next reply line that is not a comment (`//`) or an unsolicited frame; a refusal
    /// (`echo:E…`, `echo:Unknown command`) or a fault (`Error:`) fails.
    fn reply(&mut self, timeout: Duration) -> Result<String, Error> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let line = self.read_line(left.max(Duration::from_millis(1)))?;
            if line.starts_with("Error:")
                || line.starts_with("echo:E")
                || line.starts_with("echo:Unknown")
            {
                return Err(Error(format!("the firmware refused or faulted: {line}")));
            }
            if line.starts_with("//") || line.starts_with("N55") || line.is_empty() {
                continue;
            }
            return Ok(line);
        }
    }

    /// Send `text` as an unnumbered line that reports (`M114`): the report line, then its `ok`.
    fn query(&mut self, text: &str) -> Result<String, Error> {
        let report = self.command(text)?;
        if report.starts_with("ok") {
            return Err(Error(format!(
                "`{text}`: expected a report, got {report:?}"
            )));
        }
        let ok = self
            .reply(REPLY_TIMEOUT)
            .map_err(|e| Error(format!("`{text}`: {e}")))?;
        if ok == "ok" {
            Ok(report)
        } else {
            Err(Error(format!("`{text}`: expected ok, got {ok:?}")))
        }
    }

    /// Send `text` as an unnumbered line and expect `ok …`, or a report line (which an `ok`
    /// follows: [`QemuBoard::query`]).
    fn command(&mut self, text: &str) -> Result<String, Error> {
        self.send(format!("{text}\n").as_bytes())?;
        let reply = self
            .reply(REPLY_TIMEOUT)
            .map_err(|e| Error(format!("`{text}`: {e}")))?;
        if reply.starts_with("ok") || reply.starts_with("X:") {
            Ok(reply)
        } else {
            Err(Error(format!("`{text}`: expected ok, got {reply:?}")))
        }
    }

    /// Stream `program` as `forja send` does ([`send_program`] with the settings of a serial
    /// link, [`Config::default`]), the first copy of line `damage` sent with a damaged check.
    /// Returns the client's report and what it told as it went.
    fn stream(&mut self, program: &Program, damage: u32) -> Result<(SendReport, Notices), Error> {
        let stream = self
            .link
            .get_ref()
            .try_clone()
            .map_err(|e| err("host link", e))?;
        let buffered = self.link.buffer().to_vec();
        self.link.consume(buffered.len());
        let mut conn = Connection::new(Box::new(ClientLink {
            stream,
            buffered,
            damage: Some(damage),
        }));
        let mut notices = Notices::default();
        let report = send_program(&mut conn, program, Config::default(), &mut notices)
            .map_err(|e| Error(format!("forja send: {e}")))?;
        Ok((report, notices))
    }

    /// Send a frame (and a newline).
    fn frame(&mut self, msg: &forja_protocol::frame::ClientMessage<'_>) -> Result<(), Error> {
        let mut buf = [0u8; forja_protocol::frame::FRAME_LEN];
        msg.encode(&mut buf)
            .map_err(|e| Error(format!("encode {msg:?}: {e:?}")))?;
        let mut bytes = buf.to_vec();
        bytes.push(b'\n');
        self.send(&bytes)
    }

    /// Ask for message `message_type` (frame 04) and return the answer.
    fn request(&mut self, message_type: u8) -> Result<String, Error> {
        use forja_protocol::frame::ClientMessage;
        self.frame(&ClientMessage::Request { message_type })?;
        let reply = self.reply(REPLY_TIMEOUT)?;
        if reply.starts_with(&format!("N{message_type}")) {
            Ok(reply)
        } else {
            Err(Error(format!(
                "04 {message_type}: unexpected answer {reply:?}"
            )))
        }
    }

    /// Poll frame 51 until it reads `target` (to 1e-3 mm), or fail after [`MOTION_TIMEOUT`].
    fn wait_at(&mut self, target: &Position, what: &str) -> Result<Position, Error> {
        let deadline = Instant::now() + MOTION_TIMEOUT;
        loop {
            let p = parse_positions(&self.request(51)?)?;
            if p.iter().zip(target).all(|(a, b)| (a - b).abs() <= 5e-4) {
                return Ok(p);
            }
            if Instant::now() > deadline {
                return Err(Error(format!(
                    "{what}: the machine did not reach {} within {MOTION_TIMEOUT:?} (at {})",
                    show(target),
                    show(&p)
                )));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

/// What the end-to-end test measured, for the report.
#[derive(Debug)]
pub struct EndToEnd {
    /// Final `M114` of the QEMU board.
    pub m114: Position,
    /// Final frame 51 of the QEMU board.
    pub positions: Position,
    /// The simulator's final positions of the same job, from its start.
    pub simulated: Position,
    /// Wall time of the streamed job, of the upload and of the program run.
    pub times: [Duration; 3],
}

/// The same job and program, run through the simulator's firmware over its in-memory link
/// (`forja_simulator::run::run_job`), on the simulator's default machine: the final position of each
/// axis, from where the machine started.
pub fn simulate() -> Result<(Position, forja_sim_hal::MachineConfig), Error> {
    use forja_simulator::run::{JobOptions, run_job};
    let config = forja_sim_hal::MachineConfig::default_router();
    let text: String = JOB
        .iter()
        .chain(PROGRAM)
        .map(|l| format!("{l}\n"))
        .collect();
    let job = forja_simulator::Job::from_text("qemu end-to-end", text);
    let options = JobOptions {
        home_first: false,
        ..JobOptions::default()
    };
    let run = run_job(&config, &job, &options).map_err(|e| Error(format!("simulator: {e}")))?;
    if !run.is_clean() {
        return Err(Error(format!("the simulator's run was not clean:\n{run}")));
    }
    let mut out = [0.0; 4];
    for (i, letter) in AXES.iter().enumerate() {
        let axis = config
            .axis_index(*letter)
            .ok_or_else(|| Error(format!("simulator machine without axis {letter}")))?;
        let start = config.axes[axis].start_mm;
        let at = run
            .axes
            .iter()
            .find(|a| a.0 == *letter)
            .map(|a| a.1)
            .ok_or_else(|| Error(format!("simulator run without axis {letter}")))?;
        out[i] = at - start;
    }
    Ok((out, config))
}

/// The end-to-end test: boot the image, stream [`JOB`] as `forja send` does (with line
/// [`CORRUPTED`] sent damaged once), check `M114`, upload [`PROGRAM`] with frames 03, run it with 02 `Start`, poll 04 → 52
/// until it is done, read `M114` and 51, and compare them with the simulator's run of the same
/// job and program on the same machine (steps per mm read from the board with frame 00).
pub fn end_to_end(elf: &Path) -> Result<EndToEnd, Error> {
    use forja_protocol::frame::{Action, ClientMessage, ControllerMessage};

    let (simulated, sim_config) = simulate()?;
    let mut board = QemuBoard::boot(elf)?;
    eprintln!(
        "booted; `start` received on 127.0.0.1:{}",
        board.link_port()
    );

    // The board's machine has the simulator machine's steps per mm.
    for letter in AXES {
        let key = format!("{}.steps_per_mm", letter.to_ascii_lowercase());
        board.frame(&ClientMessage::ReadSetting { key: &key })?;
        let reply = board.reply(REPLY_TIMEOUT)?;
        let value = match ControllerMessage::decode(reply.as_bytes()) {
            Ok(ControllerMessage::Setting { value, .. }) => value.parse::<f64>().ok(),
            _ => None,
        }
        .ok_or_else(|| Error(format!("00 {key}: unexpected answer {reply:?}")))?;
        let sim = sim_config
            .axis_index(letter)
            .map(|i| sim_config.axes[i].steps_per_mm);
        if sim != Some(value) {
            return Err(Error(format!(
                "{key}: the board has {value}, the simulator machine {sim:?}"
            )));
        }
    }

    // Stream the job with the client's streamer: the damaged line is asked for again, once,
    // and every line is taken, none refused.
    let started = Instant::now();
    let text: String = JOB.iter().map(|l| format!("{l}\n")).collect();
    let program = Program::parse(text.as_bytes()).map_err(|e| Error(format!("JOB: {e}")))?;
    let (report, notices) = board.stream(&program, CORRUPTED)?;
    let resends: Vec<&String> = notices
        .0
        .iter()
        .filter(|n| n.starts_with("resending") || n.starts_with("no answer"))
        .collect();
    let stats = report.stats;
    if resends != [&format!("resending from line {CORRUPTED}")] || stats.rewinds != 1 {
        return Err(Error(format!(
            "line {CORRUPTED} with a damaged check: expected one resend from it, got {resends:?} \
             ({stats:?})"
        )));
    }
    if !report.refused.is_empty() || stats.stalls != 0 {
        return Err(Error(format!(
            "the job was not taken cleanly: refused {:?} ({stats:?})",
            report.refused
        )));
    }
    let m114 = parse_m114(&board.query("M114")?)?;
    let streamed = board.wait_at(&m114, "streamed job")?;
    let stream_time = started.elapsed();
    eprintln!(
        "streamed {} lines with forja send's streamer in {:.1} s ({} bytes, {} resend, {} lines \
         sent again); M114 {}; 51 {}",
        report.lines,
        stream_time.as_secs_f64(),
        stats.bytes_sent,
        stats.rewinds,
        stats.lines_resent,
        show(&m114),
        show(&streamed)
    );

    // Upload the program.
    let started = Instant::now();
    let total = PROGRAM.len() as u16;
    for (i, text) in PROGRAM.iter().enumerate() {
        board.frame(&ClientMessage::LoadLine {
            index: i as u16 + 1,
            text,
            total,
        })?;
        // Give the firmware time to store the line (the link has no flow control for frames).
        std::thread::sleep(Duration::from_millis(20));
    }
    let confirm = board.reply(REPLY_TIMEOUT)?;
    if !matches!(
        ControllerMessage::decode(confirm.as_bytes()),
        Ok(ControllerMessage::Confirm { what: "Gcode-load" })
    ) {
        return Err(Error(format!(
            "upload of {total} lines: expected 53 Confirm:Gcode-load, got {confirm:?}"
        )));
    }
    let upload_time = started.elapsed();

    // Run it, and poll its progress until its last line has run.
    let started = Instant::now();
    board.frame(&ClientMessage::Action(Action::Start))?;
    let deadline = started + MOTION_TIMEOUT;
    let progress = loop {
        let frame = board.request(52)?;
        let p = match ControllerMessage::decode(frame.as_bytes()) {
            Ok(ControllerMessage::Progress(p)) => p,
            other => {
                return Err(Error(format!(
                    "expected frame 52, got {frame:?} ({other:?})"
                )));
            }
        };
        if p.total_lines != u32::from(total) {
            return Err(Error(format!(
                "52 reports {} lines stored, not {total}",
                p.total_lines
            )));
        }
        if p.current_line == p.total_lines {
            break p;
        }
        if Instant::now() > deadline {
            return Err(Error(format!(
                "the program did not finish within {MOTION_TIMEOUT:?} (last 52: {frame})"
            )));
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let m114 = parse_m114(&board.query("M114")?)?;
    let positions = board.wait_at(&m114, "program")?;
    let run_time = started.elapsed();
    eprintln!(
        "program: {total} lines uploaded in {:.1} s, run in {:.1} s (52: {} of {} lines, \
         estimated {} s)",
        upload_time.as_secs_f64(),
        run_time.as_secs_f64(),
        progress.current_line,
        progress.total_lines,
        progress.estimated_s
    );

    // Nothing was lost on the link.
    let counters = board.read_symbol_words("FORJA_LINK_COUNTERS", 6)?;
    if counters[4] != 0 || counters[5] != 0 {
        return Err(Error(format!(
            "link counters [rx_bytes, oks, frames, garbage, overruns, uart errors] {counters:?}: \
             bytes were lost"
        )));
    }
    if !board.is_running() {
        return Err(Error("the firmware reset (QEMU ended)".into()));
    }

    // The same positions as the simulator's, to the precision of each report.
    for (i, letter) in AXES.iter().enumerate() {
        let sim = simulated[i];
        if (m114[i] - sim).abs() > 0.0005 + 1e-9 || (positions[i] - sim).abs() > 0.00005 + 1e-9 {
            return Err(Error(format!(
                "axis {letter}: QEMU M114 {:.3}, 51 {:.4}; simulator {sim:.4}\n  QEMU M114 {}\n  QEMU 51   {}\n  simulator {}",
                m114[i],
                positions[i],
                show(&m114),
                show(&positions),
                show(&simulated)
            )));
        }
    }
    Ok(EndToEnd {
        m114,
        positions,
        simulated,
        times: [stream_time, upload_time, run_time],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_check_of_the_named_line_is_damaged_and_stays_in_range() {
        let bytes = b"N9 G0 Z2*56\r\nN10 G0 X10 Y6.25*255\r\nN100 G90*12\r\n";
        let damaged = damage_check(bytes, 10).unwrap();
        assert_eq!(
            damaged,
            b"N9 G0 Z2*56\r\nN10 G0 X10 Y6.25*254\r\nN100 G90*12\r\n"
        );
        assert_eq!(
            damage_check(b"\r\nN10 G21*65535\r\n", 10).unwrap(),
            b"\r\nN10 G21*65534\r\n"
        );
        assert_eq!(damage_check(bytes, 1), None);
        assert_eq!(damage_check(b"N100 G90*12\r\n", 10), None);
        assert_eq!(damage_check(b"N10 G90\r\n", 10), None);
    }
}
