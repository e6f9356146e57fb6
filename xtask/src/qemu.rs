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
//! It uses the standard library and the `object` crate only.

use std::fmt;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

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

    /// Drain whatever the firmware sent and is waiting, without blocking for long.
    pub fn drain(&mut self) -> Vec<u8> {
        let mut out = Vec::new();
        let _ = self
            .link
            .get_ref()
            .set_read_timeout(Some(Duration::from_millis(50)));
        let mut buf = [0u8; 256];
        while let Ok(n) = self.link.read(&mut buf) {
            if n == 0 {
                break;
            }
            out.extend_from_slice(&buf[..n]);
        }
        out
    }
}

impl Drop for QemuBoard {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
