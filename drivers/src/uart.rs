//! Byte queues between a UART's interrupts and the protocol task.
//!
//! A [`UartBuffers`] holds two [`bbqueue`] byte queues and lives in a `static`. Split once at
//! start-up, it gives four handles, one per context:
//!
//! | handle | owner | does |
//! |---|---|---|
//! | [`UartRxIrq`] | receive interrupt | [`UartRxIrq::push`]es received bytes; never blocks; counts overruns when full |
//! | [`UartReader`] | protocol task | `embedded_io::{Read, ReadReady}` over the received bytes |
//! | [`UartWriter`] | protocol task | `embedded_io::{Write, WriteReady}` into the transmit queue |
//! | [`UartTxIrq`] | transmit-empty interrupt | [`UartTxIrq::pop`]s the next byte to send |
//!
//! ```
//! use forja_drivers::uart::UartBuffers;
//!
//! static UART: UartBuffers<256, 128> = UartBuffers::new();
//!
//! let parts = UART.split().expect("split once");
//! // The receive interrupt:
//! let mut rx_irq = parts.rx_irq;
//! rx_irq.push(b'G');
//! // The protocol task:
//! let mut reader = parts.reader;
//! let mut buf = [0u8; 16];
//! assert_eq!(reader.try_read(&mut buf), 1);
//! ```
//!
//! # Coordination
//!
//! The queues use bbqueue's critical-section coordination, so that the same code runs on
//! targets without compare-and-swap atomics (RISC-V `imc`, Cortex-M0) and on those with them.
//! The critical section is held only while a grant is taken or released (a few dozen
//! instructions), never while bytes are copied. The firmware binary provides the
//! `critical-section` implementation (`cortex-m`'s `critical-section-single-core` feature,
//! esp-hal's own); host tests use `critical-section`'s `std` feature.
//!
//! # Kicking the transmitter
//!
//! A UART raises its transmit-empty interrupt only while that interrupt is enabled, and a board
//! disables it when the queue runs dry. [`UartWriter::with_kick`] registers a function that the
//! writer calls after queueing bytes: it re-enables (or pends) the transmit interrupt. Without
//! it, the board must do so after each write.

use core::convert::Infallible;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use bbqueue::BBQueue;
use bbqueue::prod_cons::stream::{StreamConsumer, StreamProducer};
use bbqueue::traits::coordination::cs::CsCoord;
use bbqueue::traits::notifier::polling::Polling;
use bbqueue::traits::storage::Inline;

/// The byte queue type used by [`UartBuffers`]: inline storage of `N` bytes, critical-section
/// coordination, polling (no async wake-ups).
pub type LinkQueue<const N: usize> = BBQueue<Inline<N>, CsCoord, Polling>;

/// Receive and transmit queues of one UART, with `RX` and `TX` bytes of storage.
///
/// Put it in a `static` and [`split`](UartBuffers::split) it once.
pub struct UartBuffers<const RX: usize, const TX: usize> {
    rx: LinkQueue<RX>,
    tx: LinkQueue<TX>,
    /// Bytes dropped because the receive queue was full. Written only by the receive
    /// interrupt (load and store, no read-modify-write atomics needed).
    rx_overruns: AtomicU32,
    /// Bytes committed to the transmit queue; written only by the writer.
    tx_queued: AtomicU32,
    /// Bytes taken from the transmit queue; written only by the transmit interrupt.
    tx_sent: AtomicU32,
    taken: AtomicBool,
}

impl<const RX: usize, const TX: usize> Default for UartBuffers<RX, TX> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const RX: usize, const TX: usize> UartBuffers<RX, TX> {
    /// Empty queues.
    pub const fn new() -> Self {
        Self {
            rx: LinkQueue::new(),
            tx: LinkQueue::new(),
            rx_overruns: AtomicU32::new(0),
            tx_queued: AtomicU32::new(0),
            tx_sent: AtomicU32::new(0),
            taken: AtomicBool::new(false),
        }
    }

    /// The four handles; `None` after the first call, so that each queue has exactly one
    /// producer and one consumer.
    ///
    /// Context: thread (board set-up). Takes a critical section for a few instructions.
    pub fn split(&self) -> Option<UartParts<'_, RX, TX>> {
        let first = critical_section::with(|_| {
            let first = !self.taken.load(Ordering::Relaxed);
            self.taken.store(true, Ordering::Relaxed);
            first
        });
        first.then(|| UartParts {
            rx_irq: UartRxIrq {
                queue: self.rx.stream_producer(),
                overruns: &self.rx_overruns,
            },
            reader: UartReader {
                queue: self.rx.stream_consumer(),
                overruns: &self.rx_overruns,
            },
            writer: UartWriter {
                queue: self.tx.stream_producer(),
                queued: &self.tx_queued,
                sent: &self.tx_sent,
                kick: None,
            },
            tx_irq: UartTxIrq {
                queue: self.tx.stream_consumer(),
                sent: &self.tx_sent,
            },
        })
    }
}

/// The four handles of a [`UartBuffers`], one per execution context.
pub struct UartParts<'a, const RX: usize, const TX: usize> {
    /// For the receive interrupt.
    pub rx_irq: UartRxIrq<'a, RX>,
    /// For the protocol task: received bytes.
    pub reader: UartReader<'a, RX>,
    /// For the protocol task: bytes to send.
    pub writer: UartWriter<'a, TX>,
    /// For the transmit-empty interrupt.
    pub tx_irq: UartTxIrq<'a, TX>,
}

/// Copy as much of `bytes` into `queue` as fits; returns how much did. Never blocks: at most
/// two grants, up to the end of the ring and then from its start.
fn enqueue<const N: usize>(queue: &StreamProducer<&LinkQueue<N>>, bytes: &[u8]) -> usize {
    let mut done = 0;
    while let Some(rest) = bytes.get(done..).filter(|r| !r.is_empty()) {
        let Ok(mut grant) = queue.grant_max_remaining(rest.len()) else {
            break;
        };
        let n = grant.len().min(rest.len());
        if let (Some(dst), Some(src)) = (grant.get_mut(..n), rest.get(..n)) {
            dst.copy_from_slice(src);
        }
        grant.commit(n);
        done += n;
    }
    done
}

/// The receive interrupt's end of the receive queue.
pub struct UartRxIrq<'a, const N: usize> {
    queue: StreamProducer<&'a LinkQueue<N>>,
    overruns: &'a AtomicU32,
}

impl<const N: usize> UartRxIrq<'_, N> {
    /// Queue one received byte. `false` when the queue is full: the byte is dropped and counted
    /// as an overrun.
    ///
    /// Context: the receive interrupt. Never blocks.
    pub fn push(&mut self, byte: u8) -> bool {
        self.push_slice(&[byte]) == 1
    }

    /// Queue the bytes of a FIFO or DMA burst; returns how many fit. The rest are dropped and
    /// counted as overruns.
    ///
    /// Context: the receive interrupt. Never blocks.
    pub fn push_slice(&mut self, bytes: &[u8]) -> usize {
        let done = enqueue(&self.queue, bytes);
        let dropped = bytes.len() - done;
        if dropped > 0 {
            // Single writer: a plain load and store is a correct increment.
            let total = self.overruns.load(Ordering::Relaxed);
            self.overruns
                .store(total.wrapping_add(dropped as u32), Ordering::Relaxed);
        }
        done
    }
}

/// The protocol task's end of the receive queue.
///
/// [`ReadReady::read_ready`](embedded_io::ReadReady::read_ready) tells whether bytes are
/// waiting; [`Read::read`](embedded_io::Read::read) then returns what is there without waiting.
/// Called on an empty queue, `read` waits (spinning) for the receive interrupt, as the
/// `embedded-io` contract requires; [`UartReader::try_read`] never waits.
pub struct UartReader<'a, const N: usize> {
    queue: StreamConsumer<&'a LinkQueue<N>>,
    overruns: &'a AtomicU32,
}

impl<const N: usize> UartReader<'_, N> {
    /// Copy the received bytes into `buf`, as many as fit; `0` when none are waiting.
    ///
    /// Context: thread. Never blocks.
    pub fn try_read(&mut self, buf: &mut [u8]) -> usize {
        let mut done = 0;
        while let Some(dst) = buf.get_mut(done..).filter(|d| !d.is_empty()) {
            let Ok(grant) = self.queue.read() else {
                break;
            };
            let n = grant.len().min(dst.len());
            if let (Some(d), Some(s)) = (dst.get_mut(..n), grant.get(..n)) {
                d.copy_from_slice(s);
            }
            grant.release(n);
            done += n;
        }
        done
    }

    /// Bytes dropped so far because the receive queue was full (wrapping). A protocol that
    /// sees this change knows that the stream lost bytes and resynchronises.
    ///
    /// Context: either.
    pub fn overruns(&self) -> u32 {
        self.overruns.load(Ordering::Relaxed)
    }
}

impl<const N: usize> embedded_io::ErrorType for UartReader<'_, N> {
    type Error = Infallible;
}

impl<const N: usize> embedded_io::ReadReady for UartReader<'_, N> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        Ok(self.queue.read().is_ok())
    }
}

impl<const N: usize> embedded_io::Read for UartReader<'_, N> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        Ok(read_blocking(buf, |b| self.try_read(b)))
    }
}

/// The blocking `embedded_io::Read` of a link whose bytes another context delivers (an
/// interrupt, another task): `try_read` until it gives at least one byte; `0` only for an
/// empty `buf`.
///
/// Context: thread. Blocks, spinning, until a byte arrives: the controller never calls it
/// without `read_ready`.
pub fn read_blocking(buf: &mut [u8], mut try_read: impl FnMut(&mut [u8]) -> usize) -> usize {
    if buf.is_empty() {
        return 0;
    }
    loop {
        let n = try_read(buf);
        if n > 0 {
            return n;
        }
        core::hint::spin_loop();
    }
}

/// The protocol task's end of the transmit queue.
///
/// [`WriteReady::write_ready`](embedded_io::WriteReady::write_ready) tells whether at least one
/// byte fits; [`Write::write`](embedded_io::Write::write) then queues what fits without
/// waiting. Called on a full queue, `write` waits (spinning) for the transmit interrupt to make
/// room, and `flush` waits until the interrupt has taken every byte: both need the interrupt to
/// run, so never call them from a context that masks it. [`UartWriter::try_write`] never waits.
pub struct UartWriter<'a, const N: usize> {
    queue: StreamProducer<&'a LinkQueue<N>>,
    queued: &'a AtomicU32,
    sent: &'a AtomicU32,
    kick: Option<fn()>,
}

impl<'a, const N: usize> UartWriter<'a, N> {
    /// Call `kick` after queueing bytes and while waiting for room: it enables or pends the
    /// transmit-empty interrupt.
    #[must_use]
    pub fn with_kick(mut self, kick: fn()) -> Self {
        self.kick = Some(kick);
        self
    }

    /// Queue as much of `bytes` as fits; returns how much did (`0` when the queue is full).
    ///
    /// Context: thread. Never blocks.
    pub fn try_write(&mut self, bytes: &[u8]) -> usize {
        let done = enqueue(&self.queue, bytes);
        if done > 0 {
            let total = self.queued.load(Ordering::Relaxed);
            self.queued
                .store(total.wrapping_add(done as u32), Ordering::Release);
            self.kick();
        }
        done
    }

    /// Bytes queued and not yet taken by the transmit interrupt.
    ///
    /// Context: thread.
    pub fn pending(&self) -> usize {
        let queued = self.queued.load(Ordering::Relaxed);
        let sent = self.sent.load(Ordering::Acquire);
        queued.wrapping_sub(sent) as usize
    }

    fn kick(&self) {
        if let Some(kick) = self.kick {
            kick();
        }
    }
}

impl<const N: usize> embedded_io::ErrorType for UartWriter<'_, N> {
    type Error = Infallible;
}

impl<const N: usize> embedded_io::WriteReady for UartWriter<'_, N> {
    fn write_ready(&mut self) -> Result<bool, Self::Error> {
        // A grant dropped uncommitted gives its space back.
        Ok(self.queue.grant_max_remaining(1).is_ok())
    }
}

impl<const N: usize> embedded_io::Write for UartWriter<'_, N> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        if buf.is_empty() {
            return Ok(0);
        }
        loop {
            let n = self.try_write(buf);
            if n > 0 {
                return Ok(n);
            }
            self.kick();
            core::hint::spin_loop();
        }
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        while self.pending() > 0 {
            self.kick();
            core::hint::spin_loop();
        }
        Ok(())
    }
}

/// The transmit-empty interrupt's end of the transmit queue.
pub struct UartTxIrq<'a, const N: usize> {
    queue: StreamConsumer<&'a LinkQueue<N>>,
    sent: &'a AtomicU32,
}

impl<const N: usize> UartTxIrq<'_, N> {
    /// The next byte to send, `None` when the queue is empty (the interrupt then disables
    /// itself until the writer kicks it).
    ///
    /// Context: the transmit-empty interrupt. Never blocks.
    pub fn pop(&mut self) -> Option<u8> {
        let mut byte = None;
        self.drain_with(|bytes| {
            byte = bytes.first().copied();
            usize::from(byte.is_some())
        });
        byte
    }

    /// Hand the waiting bytes (one contiguous run of them) to `send`, which returns how many it
    /// took: to fill a hardware FIFO or start a DMA transfer. Returns that count, `0` when the
    /// queue is empty.
    ///
    /// Context: the transmit-empty interrupt. Never blocks.
    pub fn drain_with(&mut self, send: impl FnOnce(&[u8]) -> usize) -> usize {
        let Ok(grant) = self.queue.read() else {
            return 0;
        };
        let n = send(&grant).min(grant.len());
        grant.release(n);
        if n > 0 {
            let total = self.sent.load(Ordering::Relaxed);
            self.sent
                .store(total.wrapping_add(n as u32), Ordering::Release);
        }
        n
    }

    /// Whether nothing waits to be sent.
    ///
    /// Context: either.
    pub fn is_empty(&self) -> bool {
        self.queue.read().is_err()
    }
}

/// A UART host link as a controller takes it: the thread ends of the two queues joined into one
/// `embedded-io` `Read + ReadReady + Write`, counting the bytes received.
///
/// Context: the thread that runs the controller.
pub struct UartLink<'a, const RX: usize, const TX: usize> {
    reader: UartReader<'a, RX>,
    writer: UartWriter<'a, TX>,
    received: u32,
}

impl<'a, const RX: usize, const TX: usize> UartLink<'a, RX, TX> {
    /// Join the two ends.
    pub fn new(reader: UartReader<'a, RX>, writer: UartWriter<'a, TX>) -> Self {
        Self {
            reader,
            writer,
            received: 0,
        }
    }

    /// Whether received bytes wait in the queue.
    pub fn has_input(&mut self) -> bool {
        embedded_io::ReadReady::read_ready(&mut self.reader).unwrap_or(false)
    }

    /// Bytes read so far (wrapping).
    pub fn received(&self) -> u32 {
        self.received
    }

    /// Bytes the receive queue had no room for (see [`UartReader::overruns`]).
    pub fn overruns(&self) -> u32 {
        self.reader.overruns()
    }
}

impl<const RX: usize, const TX: usize> embedded_io::ErrorType for UartLink<'_, RX, TX> {
    type Error = Infallible;
}

impl<const RX: usize, const TX: usize> embedded_io::Read for UartLink<'_, RX, TX> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = self.reader.read(buf)?;
        self.received = self.received.wrapping_add(n as u32);
        Ok(n)
    }
}

impl<const RX: usize, const TX: usize> embedded_io::ReadReady for UartLink<'_, RX, TX> {
    fn read_ready(&mut self) -> Result<bool, Self::Error> {
        self.reader.read_ready()
    }
}

impl<const RX: usize, const TX: usize> embedded_io::Write for UartLink<'_, RX, TX> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.writer.write(buf)
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        self.writer.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_io::{Read, ReadReady, Write, WriteReady};
    use std::sync::atomic::AtomicUsize;

    fn leak<const RX: usize, const TX: usize>() -> &'static UartBuffers<RX, TX> {
        Box::leak(Box::new(UartBuffers::new()))
    }

    #[test]
    fn splits_once() {
        let b = leak::<8, 8>();
        assert!(b.split().is_some());
        assert!(b.split().is_none());
    }

    #[test]
    fn handles_can_move_to_other_contexts() {
        fn assert_send<T: Send>() {}
        assert_send::<UartRxIrq<'static, 8>>();
        assert_send::<UartReader<'static, 8>>();
        assert_send::<UartWriter<'static, 8>>();
        assert_send::<UartTxIrq<'static, 8>>();
        fn assert_sync<T: Sync>() {}
        assert_sync::<UartBuffers<8, 8>>();
    }

    #[test]
    fn received_bytes_reach_the_reader_in_order() {
        let p = leak::<16, 8>().split().unwrap();
        let (mut rx, mut reader) = (p.rx_irq, p.reader);
        assert!(!reader.read_ready().unwrap());
        assert_eq!(reader.try_read(&mut [0; 4]), 0);
        for b in b"G1 X5\n" {
            assert!(rx.push(*b));
        }
        assert!(reader.read_ready().unwrap());
        let mut buf = [0; 4];
        assert_eq!(reader.read(&mut buf).unwrap(), 4);
        assert_eq!(&buf, b"G1 X");
        assert_eq!(reader.read(&mut buf).unwrap(), 2);
        assert_eq!(&buf[..2], b"5\n");
        assert_eq!(reader.read(&mut []).unwrap(), 0);
        assert_eq!(reader.overruns(), 0);
    }

    #[test]
    fn the_link_joins_both_ends_and_counts_what_it_read() {
        let p = leak::<8, 16>().split().unwrap();
        let (mut rx, mut tx) = (p.rx_irq, p.tx_irq);
        let mut link = UartLink::new(p.reader, p.writer);
        assert!(!link.has_input());
        assert_eq!(rx.push_slice(b"M114\n"), 5);
        assert!(link.has_input());
        let mut buf = [0; 8];
        assert_eq!(link.read(&mut buf).unwrap(), 5);
        assert_eq!(&buf[..5], b"M114\n");
        assert_eq!(link.received(), 5);
        assert_eq!(link.write(b"ok\n").unwrap(), 3);
        assert_eq!(tx.drain_with(|b| b.len()), 3);
        // The ring may leave one byte unused when the data wraps around its end.
        let taken = rx.push_slice(&[0; 10]);
        assert!((7..=8).contains(&taken), "{taken}");
        assert_eq!(link.overruns() as usize, 10 - taken);
    }

    #[test]
    fn a_full_receive_queue_drops_and_counts() {
        let p = leak::<8, 8>().split().unwrap();
        let (mut rx, mut reader) = (p.rx_irq, p.reader);
        assert_eq!(rx.push_slice(&[1, 2, 3, 4, 5, 6]), 6);
        assert_eq!(rx.push_slice(&[7, 8, 9, 10]), 2);
        assert!(!rx.push(11));
        assert_eq!(reader.overruns(), 3);
        let mut buf = [0; 16];
        assert_eq!(reader.try_read(&mut buf), 8);
        assert_eq!(&buf[..8], &[1, 2, 3, 4, 5, 6, 7, 8]);
        // Room again; the queue wraps around its end.
        assert_eq!(rx.push_slice(&[20, 21, 22, 23, 24]), 5);
        assert_eq!(reader.try_read(&mut buf), 5);
        assert_eq!(&buf[..5], &[20, 21, 22, 23, 24]);
    }

    #[test]
    fn reads_span_the_wrap_of_the_ring() {
        let p = leak::<8, 8>().split().unwrap();
        let (mut rx, mut reader) = (p.rx_irq, p.reader);
        let mut buf = [0; 8];
        for round in 0..20u8 {
            let data = [round, round + 1, round + 2, round + 3, round + 4];
            assert_eq!(rx.push_slice(&data), 5);
            assert_eq!(reader.try_read(&mut buf), 5, "round {round}");
            assert_eq!(&buf[..5], &data);
        }
    }

    #[test]
    fn written_bytes_reach_the_transmit_interrupt() {
        static KICKS: AtomicUsize = AtomicUsize::new(0);
        let p = leak::<8, 8>().split().unwrap();
        let mut writer = p.writer.with_kick(|| {
            KICKS.fetch_add(1, Ordering::Relaxed);
        });
        let mut tx = p.tx_irq;
        assert!(tx.is_empty());
        assert_eq!(tx.pop(), None);
        assert!(writer.write_ready().unwrap());
        assert_eq!(writer.write(b"ok\n").unwrap(), 3);
        assert_eq!(KICKS.load(Ordering::Relaxed), 1);
        assert_eq!(writer.pending(), 3);
        assert_eq!(tx.pop(), Some(b'o'));
        assert_eq!(tx.drain_with(|b| b.len()), 2);
        assert!(tx.is_empty());
        assert_eq!(writer.pending(), 0);
        writer.flush().unwrap();
        // Fill it up: write_ready goes false and try_write takes only what fits (the ring
        // leaves one byte unused when the data wraps around its end).
        let n = writer.try_write(&[0; 12]);
        assert!((7..=8).contains(&n), "{n}");
        assert!(!writer.write_ready().unwrap());
        assert_eq!(writer.try_write(&[1]), 0);
        assert_eq!(writer.write(&[]).unwrap(), 0);
    }

    #[test]
    fn blocking_write_and_flush_wait_for_the_interrupt() {
        let p = leak::<8, 16>().split().unwrap();
        let mut writer = p.writer;
        let mut tx = p.tx_irq;
        let message: Vec<u8> = (0..200u8).collect();
        let drain = std::thread::spawn(move || {
            let mut got = Vec::new();
            while got.len() < 200 {
                if let Some(b) = tx.pop() {
                    got.push(b);
                } else {
                    std::thread::yield_now();
                }
            }
            got
        });
        writer.write_all(&message).unwrap();
        writer.flush().unwrap();
        assert_eq!(writer.pending(), 0);
        assert_eq!(drain.join().unwrap(), message);
    }

    #[test]
    fn concurrent_receive_keeps_every_byte_in_order() {
        let p = leak::<32, 8>().split().unwrap();
        let mut rx = p.rx_irq;
        let mut reader = p.reader;
        let irq = std::thread::spawn(move || {
            let (mut next, mut refused) = (0u32, 0u32);
            while next < 10_000 {
                if rx.push((next % 251) as u8) {
                    next += 1;
                } else {
                    refused += 1;
                    std::thread::yield_now();
                }
            }
            refused
        });
        let mut expected = 0u32;
        let mut buf = [0u8; 7];
        while expected < 10_000 {
            let n = reader.read(&mut buf).unwrap();
            for b in &buf[..n] {
                assert_eq!(u32::from(*b), expected % 251);
                expected += 1;
            }
        }
        let refused = irq.join().unwrap();
        assert_eq!(
            reader.overruns(),
            refused,
            "every refused push is an overrun"
        );
    }
}
