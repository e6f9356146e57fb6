//! The pseudo-terminal link, like a firmware board's UART.
//!
//! # How Linux behaves, and what the link does with it
//!
//! A pseudo-terminal is a pair: the simulator keeps the **master**; host software (a sender,
//! a terminal program, pyserial) opens the **slave**, `/dev/pts/N`, as it would open
//! `/dev/ttyUSB0`. A terminal has no connect signal, but on Linux the master shows it:
//!
//! - while no process has the slave open, `poll` on the master reports `POLLHUP` and `read`
//!   on the master fails with `EIO`;
//! - while any process has it open, `POLLHUP` is clear;
//! - bytes the peer wrote just before closing are still readable from the master (`POLLIN`
//!   with `POLLHUP`);
//! - terminal settings set on the slave persist while the master is open, across closes and
//!   re-opens;
//! - bytes written to the master while no one has the slave open are delivered to the next
//!   process that opens it.
//!
//! So [`PtyLink::open`] sets the slave to raw mode (no echo, no line editing, no newline
//! translation, 8-bit: host software sees exactly the bytes the firmware sends), then closes
//! its own slave descriptor, which would otherwise hide every hang-up. The link counts as
//! connected while `POLLHUP` is clear. Each poll reads first, then checks for the hang-up, so
//! the last bytes of a departing peer are kept. Nothing is written while disconnected, and on
//! each new connection the master's output queue is flushed (`tcflush(TCOFLUSH)`), so a new
//! peer never reads replies meant for the previous one. A peer that opens and closes the slave
//! between two polls is never seen as connected, but its bytes are received.
//!
//! A peer that holds the slave open and stops reading fills the terminal's buffer, then the
//! link's transmit buffer; past that, writes are discarded whole and counted
//! ([`PtyLink::tx_discarded`]): the firmware never waits for it.

use std::fs::File;
use std::io::{self, Read as _, Write as _};
use std::os::fd::AsFd;
use std::path::{Path, PathBuf};

use nix::errno::Errno;
use nix::fcntl::{FcntlArg, FdFlag, OFlag, fcntl};
use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
use nix::sys::termios::{FlushArg, SetArg, cfmakeraw, tcflush, tcgetattr, tcsetattr};

use super::{BufferedPort, Buffers, buffered_link};

/// A pseudo-terminal whose slave side host software opens like a serial port.
///
/// Implements [`super::PortLink`]; see the module documentation for how connection is
/// detected. Dropping it closes the master (peers see a hang-up) and removes the symbolic link
/// made by [`PtyLink::open`], if it still points at this terminal.
#[derive(Debug)]
pub struct PtyLink {
    master: File,
    slave_path: PathBuf,
    symlink: Option<PathBuf>,
    connected: bool,
    bufs: Buffers,
    connections: u64,
    tx_discarded: u64,
}

fn errno(e: Errno) -> io::Error {
    io::Error::from(e)
}

impl PtyLink {
    /// Open a pseudo-terminal in raw mode. With `symlink`, also make a symbolic link at that
    /// path to the slave (a stable name for host software: the `/dev/pts` number changes each
    /// run); an existing symbolic link there is replaced.
    ///
    /// Errors: no pseudo-terminal could be opened or configured; `symlink` exists and is not a
    /// symbolic link (`AlreadyExists`), or cannot be created.
    pub fn open(symlink: Option<&Path>) -> io::Result<Self> {
        let pty = nix::pty::openpty(None, None).map_err(errno)?;
        let slave_path = nix::unistd::ttyname(pty.slave.as_fd()).map_err(errno)?;
        let mut termios = tcgetattr(pty.slave.as_fd()).map_err(errno)?;
        cfmakeraw(&mut termios);
        tcsetattr(pty.slave.as_fd(), SetArg::TCSANOW, &termios).map_err(errno)?;
        drop(pty.slave);

        let master = pty.master;
        let flags = fcntl(master.as_fd(), FcntlArg::F_GETFL).map_err(errno)?;
        let flags = OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK;
        fcntl(master.as_fd(), FcntlArg::F_SETFL(flags)).map_err(errno)?;
        fcntl(master.as_fd(), FcntlArg::F_SETFD(FdFlag::FD_CLOEXEC)).map_err(errno)?;

        let symlink = match symlink {
            Some(path) => {
                if let Ok(meta) = std::fs::symlink_metadata(path) {
                    if !meta.file_type().is_symlink() {
                        return Err(io::Error::new(
                            io::ErrorKind::AlreadyExists,
                            format!("{} exists and is not a symbolic link", path.display()),
                        ));
                    }
                    std::fs::remove_file(path)?;
                }
                std::os::unix::fs::symlink(&slave_path, path)?;
                Some(path.to_path_buf())
            }
            None => None,
        };

        Ok(Self {
            master: File::from(master),
            slave_path,
            symlink,
            connected: false,
            bufs: Buffers::default(),
            connections: 0,
            tx_discarded: 0,
        })
    }

    /// The slave device host software opens, e.g. `/dev/pts/7`.
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }

    /// Bytes written while a peer was connected and discarded because it had stopped reading
    /// (the transmit buffer was full).
    pub fn tx_discarded(&self) -> u64 {
        self.tx_discarded
    }

    /// The symbolic link to the slave, when one was asked for.
    pub fn symlink_path(&self) -> Option<&Path> {
        self.symlink.as_deref()
    }

    fn receive(&mut self) -> io::Result<()> {
        let mut chunk = [0u8; 4096];
        loop {
            let room = self.bufs.rx_room().min(chunk.len());
            if room == 0 {
                return Ok(());
            }
            match self.master.read(&mut chunk[..room]) {
                Ok(0) => return Ok(()),
                Ok(n) => self.bufs.rx.extend(&chunk[..n]),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(()),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                // No process has the slave open.
                Err(e) if e.raw_os_error() == Some(Errno::EIO as i32) => return Ok(()),
                Err(e) => return Err(e),
            }
        }
    }

    /// Whether a process holds the slave open now.
    fn peer_present(&self) -> io::Result<bool> {
        let mut fds = [PollFd::new(self.master.as_fd(), PollFlags::POLLIN)];
        poll(&mut fds, PollTimeout::ZERO).map_err(errno)?;
        let revents = fds[0].revents().unwrap_or(PollFlags::empty());
        Ok(!revents.contains(PollFlags::POLLHUP))
    }

    fn send(&mut self) -> io::Result<()> {
        while self.connected && !self.bufs.tx.is_empty() {
            let pending = self.bufs.tx.make_contiguous();
            match self.master.write(pending) {
                Ok(0) => return Ok(()),
                Ok(n) => {
                    self.bufs.tx.drain(..n);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(()),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.raw_os_error() == Some(Errno::EIO as i32) => {
                    self.connected = false;
                    self.bufs.tx.clear();
                }
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

impl BufferedPort for PtyLink {
    fn buffers(&mut self) -> &mut Buffers {
        &mut self.bufs
    }

    fn is_connected(&self) -> bool {
        self.connected
    }

    fn service(&mut self) -> io::Result<()> {
        self.receive()?;
        let present = self.peer_present()?;
        if present && !self.connected {
            self.connections += 1;
            tcflush(self.master.as_fd(), FlushArg::TCOFLUSH).map_err(errno)?;
        }
        if !present {
            self.bufs.tx.clear();
        }
        self.connected = present;
        self.send()
    }

    fn overflow(&mut self, lost: usize) {
        self.tx_discarded += lost as u64;
    }
}

impl Drop for PtyLink {
    fn drop(&mut self) {
        if let Some(link) = &self.symlink
            && std::fs::read_link(link).is_ok_and(|target| target == self.slave_path)
        {
            let _ = std::fs::remove_file(link);
        }
    }
}

buffered_link!(PtyLink);
