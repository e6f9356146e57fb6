//! An in-process link: a pipe pair between the firmware and a host in the same program.
//!
//! For tests and for scripted runs: the simulator can stream a job file through the very
//! protocol path a TCP or terminal host would use, without an operating-system link.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use forja_hal_abstraction::link::{LinkState, LinkStatus};

use super::PortLink;

#[derive(Debug, Default)]
struct Pipes {
    to_controller: VecDeque<u8>,
    to_host: VecDeque<u8>,
    host_open: bool,
}

#[derive(Debug, Default)]
struct Shared {
    pipes: Mutex<Pipes>,
    changed: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Pipes> {
        self.pipes.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The firmware's end of an in-process link: implements [`PortLink`].
///
/// Connected while its [`MemoryHost`] exists. [`ReadReady::read_ready`](embedded_io::ReadReady)
/// is `true` only with bytes waiting; once the host is gone and every byte read,
/// [`Read::read`](embedded_io::Read) returns `Ok(0)` (end of file) instead of blocking. Writes
/// after the host is gone are discarded. [`PortLink::poll`] has nothing to do. The two ends may
/// live on different threads.
#[derive(Debug)]
pub struct MemoryLink {
    shared: Arc<Shared>,
}

/// The host's end of an in-process link.
#[derive(Debug)]
pub struct MemoryHost {
    shared: Arc<Shared>,
}

impl MemoryLink {
    /// A connected pair: the firmware's end and the host's end.
    pub fn pair() -> (MemoryLink, MemoryHost) {
        let shared = Arc::new(Shared::default());
        shared.lock().host_open = true;
        (
            MemoryLink {
                shared: Arc::clone(&shared),
            },
            MemoryHost { shared },
        )
    }
}

impl MemoryHost {
    /// Send bytes to the firmware.
    pub fn send(&self, bytes: &[u8]) {
        self.shared.lock().to_controller.extend(bytes);
        self.shared.changed.notify_all();
    }

    /// Take every byte the firmware has sent so far.
    pub fn take_received(&self) -> Vec<u8> {
        self.shared.lock().to_host.drain(..).collect()
    }

    /// Bytes sent to the firmware and not yet read by it.
    pub fn pending_to_firmware(&self) -> usize {
        self.shared.lock().to_controller.len()
    }

    /// Wait up to `timeout` for the firmware to send something, then take it all (empty on
    /// time-out).
    pub fn recv_timeout(&self, timeout: Duration) -> Vec<u8> {
        let deadline = Instant::now() + timeout;
        let mut pipes = self.shared.lock();
        while pipes.to_host.is_empty() {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            pipes = self
                .shared
                .changed
                .wait_timeout(pipes, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        pipes.to_host.drain(..).collect()
    }
}

impl Drop for MemoryHost {
    fn drop(&mut self) {
        self.shared.lock().host_open = false;
        self.shared.changed.notify_all();
    }
}

impl embedded_io::ErrorType for MemoryLink {
    type Error = io::Error;
}

impl embedded_io::ReadReady for MemoryLink {
    fn read_ready(&mut self) -> Result<bool, io::Error> {
        Ok(!self.shared.lock().to_controller.is_empty())
    }
}

impl embedded_io::Read for MemoryLink {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, io::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        let mut pipes = self.shared.lock();
        while pipes.to_controller.is_empty() && pipes.host_open {
            pipes = self
                .shared
                .changed
                .wait(pipes)
                .unwrap_or_else(PoisonError::into_inner);
        }
        let n = buf.len().min(pipes.to_controller.len());
        for (dst, src) in buf.iter_mut().zip(pipes.to_controller.drain(..n)) {
            *dst = src;
        }
        Ok(n)
    }
}

impl embedded_io::WriteReady for MemoryLink {
    fn write_ready(&mut self) -> Result<bool, io::Error> {
        Ok(true)
    }
}

impl embedded_io::Write for MemoryLink {
    fn write(&mut self, buf: &[u8]) -> Result<usize, io::Error> {
        let mut pipes = self.shared.lock();
        if pipes.host_open {
            pipes.to_host.extend(buf);
            drop(pipes);
            self.shared.changed.notify_all();
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), io::Error> {
        Ok(())
    }
}

impl LinkStatus for MemoryLink {
    fn state(&self) -> LinkState {
        super::state(self.shared.lock().host_open)
    }
}

impl PortLink for MemoryLink {
    fn poll(&mut self) -> Result<(), io::Error> {
        Ok(())
    }

    fn connections(&self) -> u64 {
        1
    }

    fn discard_input(&mut self) -> Result<usize, io::Error> {
        Ok(self.shared.lock().to_controller.drain(..).count())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_io::{Read, ReadReady, Write};

    #[test]
    fn carries_bytes_both_ways_and_ends_with_eof() {
        let (mut fw, host) = MemoryLink::pair();
        assert_eq!(fw.state(), LinkState::Connected);
        assert!(!fw.read_ready().unwrap());
        host.send(b"G1 X1\n");
        assert_eq!(host.pending_to_firmware(), 6);
        assert!(fw.read_ready().unwrap());
        let mut buf = [0u8; 4];
        assert_eq!(fw.read(&mut buf).unwrap(), 4);
        assert_eq!(&buf, b"G1 X");
        fw.write_all(b"ok\n").unwrap();
        assert_eq!(host.take_received(), b"ok\n");
        drop(host);
        assert_eq!(fw.state(), LinkState::Disconnected);
        assert_eq!(
            fw.read(&mut buf).unwrap(),
            2,
            "bytes sent before closing stay"
        );
        assert_eq!(fw.read(&mut buf).unwrap(), 0, "then end of file");
        assert_eq!(fw.write(b"lost").unwrap(), 4);
    }

    #[test]
    fn blocking_read_waits_for_another_thread() {
        let (mut fw, host) = MemoryLink::pair();
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            host.send(b"?");
            host.recv_timeout(Duration::from_secs(5))
        });
        let mut buf = [0u8; 8];
        assert_eq!(fw.read(&mut buf).unwrap(), 1);
        fw.write_all(b"<Idle>\n").unwrap();
        assert_eq!(t.join().unwrap(), b"<Idle>\n");
    }
}
