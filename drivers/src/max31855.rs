//! MAX31855 thermocouple-to-digital converter on an `embedded-hal` SPI device.
//!
//! The worked example of `docs/writing-a-driver.md`: a [`TemperatureSensor`] for K-type (and
//! other) thermocouples on hot ends that run hotter than a thermistor allows.
//!
//! The chip converts continuously; a read clocks out one 32-bit frame (datasheet, "Memory
//! Map"):
//!
//! | bits | content |
//! |---|---|
//! | 31–18 | thermocouple temperature, 14-bit two's complement, 0.25 °C per count |
//! | 17 | reserved, always 0 |
//! | 16 | fault: one of bits 2–0 is set |
//! | 15–4 | cold-junction (internal) temperature, 12-bit two's complement, 0.0625 °C per count |
//! | 3 | reserved, always 0 |
//! | 2, 1, 0 | thermocouple shorted to VCC, shorted to GND, open |
//!
//! # Execution context
//!
//! Thread (the temperature loop). One 4-byte SPI read; blocks for the transfer (about 8 µs at
//! 5 MHz, the chip's maximum clock) and for the bus if it is shared.
//!
//! # Errors
//!
//! An SPI error is [`ErrorKind::Hardware`]. A fault reported by the chip is
//! [`ErrorKind::SensorFault`], so the heater controller shuts the heater off. A frame that the
//! chip cannot have sent (a reserved bit set, as when MISO floats high, or all zeros, as when
//! it is stuck low) is [`ErrorKind::Hardware`]: a dead bus must never read as a plausible
//! 0 °C.

use core::fmt;

use embedded_hal::spi::SpiDevice;
use forja_hal_abstraction::thermal::TemperatureSensor;
use forja_hal_abstraction::{Error, ErrorKind, ErrorType};

/// A fault the MAX31855 reports about its thermocouple.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ThermocoupleFault {
    /// No thermocouple connected, or a broken wire (bit 0).
    Open,
    /// The thermocouple touches ground (bit 1).
    ShortToGround,
    /// The thermocouple touches the supply (bit 2).
    ShortToVcc,
}

/// A [`Max31855`] read failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Max31855Error<E> {
    /// The SPI transfer failed.
    Spi(E),
    /// The chip reports a thermocouple fault.
    Thermocouple(ThermocoupleFault),
    /// The frame cannot come from the chip: the bus is dead or miswired.
    BadFrame(u32),
}

impl<E: fmt::Debug> fmt::Display for Max31855Error<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Spi(e) => write!(f, "MAX31855 SPI transfer failed: {e:?}"),
            Self::Thermocouple(fault) => write!(f, "thermocouple fault: {fault:?}"),
            Self::BadFrame(raw) => write!(f, "MAX31855 frame {raw:#010x} is invalid"),
        }
    }
}

impl<E: fmt::Debug> Error for Max31855Error<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Spi(_) | Self::BadFrame(_) => ErrorKind::Hardware,
            Self::Thermocouple(_) => ErrorKind::SensorFault,
        }
    }
}

/// One 32-bit frame read from a MAX31855, checked for bus errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Frame(u32);

impl Frame {
    /// Reserved bits 17 and 3, which the chip always sends as 0.
    const RESERVED: u32 = (1 << 17) | (1 << 3);
    const FAULT: u32 = 1 << 16;

    /// Check a raw frame: `BadFrame` when a reserved bit is set or the frame is all zeros.
    pub fn parse<E>(raw: u32) -> Result<Self, Max31855Error<E>> {
        if raw & Self::RESERVED != 0 || raw == 0 {
            return Err(Max31855Error::BadFrame(raw));
        }
        Ok(Self(raw))
    }

    /// The fault the chip reports, if any.
    pub fn fault(self) -> Option<ThermocoupleFault> {
        if self.0 & Self::FAULT == 0 {
            None
        } else if self.0 & 0b001 != 0 {
            Some(ThermocoupleFault::Open)
        } else if self.0 & 0b010 != 0 {
            Some(ThermocoupleFault::ShortToGround)
        } else {
            // Bit 2, or a fault bit with no cause: treat it as the remaining cause.
            Some(ThermocoupleFault::ShortToVcc)
        }
    }

    /// Thermocouple (hot-junction) temperature, in millidegrees Celsius.
    pub fn thermocouple_mc(self) -> i32 {
        // Arithmetic shift sign-extends the 14-bit field; 250 m°C per count.
        ((self.0 as i32) >> 18) * 250
    }

    /// Cold-junction (chip) temperature, in millidegrees Celsius, rounded toward zero.
    pub fn internal_mc(self) -> i32 {
        // Move bits 15–4 to the top, sign-extend down; 62.5 m°C per count.
        let counts = ((self.0 << 16) as i32) >> 20;
        counts * 625 / 10
    }
}

/// A MAX31855 on an SPI bus (mode 0, at most 5 MHz, read-only: MOSI is not used).
pub struct Max31855<SPI> {
    spi: SPI,
}

impl<SPI: SpiDevice> Max31855<SPI> {
    /// A converter on `spi`, which asserts the chip select around each transfer.
    pub fn new(spi: SPI) -> Self {
        Self { spi }
    }

    /// Read and check one frame.
    ///
    /// Context: thread. Blocks for one SPI transfer.
    /// Errors: [`Max31855Error::Spi`], [`Max31855Error::BadFrame`].
    pub fn read_frame(&mut self) -> Result<Frame, Max31855Error<SPI::Error>> {
        let mut bytes = [0u8; 4];
        self.spi.read(&mut bytes).map_err(Max31855Error::Spi)?;
        Frame::parse(u32::from_be_bytes(bytes))
    }

    /// Give the SPI device back.
    pub fn release(self) -> SPI {
        self.spi
    }
}

impl<SPI: SpiDevice> ErrorType for Max31855<SPI> {
    type Error = Max31855Error<SPI::Error>;
}

impl<SPI: SpiDevice> TemperatureSensor for Max31855<SPI> {
    fn read_millicelsius(&mut self) -> Result<i32, Self::Error> {
        let frame = self.read_frame()?;
        match frame.fault() {
            Some(fault) => Err(Max31855Error::Thermocouple(fault)),
            None => Ok(frame.thermocouple_mc()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::spi::{self, ErrorType as SpiErrorType, Operation};
    use std::collections::VecDeque;

    /// An SPI device that answers each read with the next scripted frame.
    struct FakeSpi {
        frames: VecDeque<Result<u32, spi::ErrorKind>>,
    }

    impl FakeSpi {
        fn new(frames: &[Result<u32, spi::ErrorKind>]) -> Self {
            Self {
                frames: frames.iter().copied().collect(),
            }
        }
    }

    impl SpiErrorType for FakeSpi {
        type Error = spi::ErrorKind;
    }

    impl SpiDevice for FakeSpi {
        fn transaction(&mut self, operations: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
            let frame = self.frames.pop_front().expect("unscripted SPI read")?;
            match operations {
                [Operation::Read(buf)] if buf.len() == 4 => {
                    buf.copy_from_slice(&frame.to_be_bytes());
                    Ok(())
                }
                other => panic!("unexpected SPI operations: {}", other.len()),
            }
        }
    }

    /// A frame from the datasheet's two temperature fields (in counts) and low bits.
    fn frame(tc_counts: i16, internal_counts: i16, low_bits: u32) -> u32 {
        let tc = (u32::from(tc_counts as u16) & 0x3FFF) << 18;
        let internal = (u32::from(internal_counts as u16) & 0x0FFF) << 4;
        tc | internal | low_bits
    }

    #[test]
    fn decodes_the_datasheet_examples() {
        // Thermocouple: 0.25 °C per count.
        for (counts, mc) in [
            (6400, 1_600_000),
            (400, 100_000),
            (100, 25_000),
            (-1, -250),
            (-4, -1_000),
            (-1000, -250_000),
        ] {
            let f = Frame::parse::<()>(frame(counts, 400, 0)).unwrap();
            assert_eq!(f.thermocouple_mc(), mc, "{counts} counts");
        }
        // Cold junction: 0.0625 °C per count.
        for (counts, mc) in [(2032, 127_000), (400, 25_000), (-1, -62), (-880, -55_000)] {
            let f = Frame::parse::<()>(frame(100, counts, 0)).unwrap();
            assert_eq!(f.internal_mc(), mc, "{counts} counts");
        }
    }

    #[test]
    fn reads_the_thermocouple_temperature() {
        let mut sensor = Max31855::new(FakeSpi::new(&[Ok(frame(840, 400, 0))]));
        assert_eq!(sensor.read_millicelsius(), Ok(210_000));
        assert!(sensor.release().frames.is_empty());
    }

    #[test]
    fn chip_faults_are_sensor_faults() {
        let fault = 1 << 16;
        for (bits, expected) in [
            (0b001, ThermocoupleFault::Open),
            (0b010, ThermocoupleFault::ShortToGround),
            (0b100, ThermocoupleFault::ShortToVcc),
        ] {
            let mut sensor = Max31855::new(FakeSpi::new(&[Ok(frame(0, 400, fault | bits))]));
            let e = sensor.read_millicelsius().unwrap_err();
            assert_eq!(e, Max31855Error::Thermocouple(expected));
            assert_eq!(e.kind(), ErrorKind::SensorFault);
        }
    }

    #[test]
    fn a_dead_bus_is_a_hardware_fault_not_zero_degrees() {
        for raw in [0x0000_0000, 0xFFFF_FFFF, frame(100, 400, 1 << 3)] {
            let mut sensor = Max31855::new(FakeSpi::new(&[Ok(raw)]));
            let e = sensor.read_millicelsius().unwrap_err();
            assert_eq!(e, Max31855Error::BadFrame(raw));
            assert_eq!(e.kind(), ErrorKind::Hardware);
        }
        let mut sensor = Max31855::new(FakeSpi::new(&[Err(spi::ErrorKind::Overrun)]));
        let e = sensor.read_millicelsius().unwrap_err();
        assert_eq!(e, Max31855Error::Spi(spi::ErrorKind::Overrun));
        assert_eq!(e.kind(), ErrorKind::Hardware);
        assert!(e.to_string().contains("SPI"));
    }

    #[test]
    fn the_guide_quotes_this_file_verbatim() {
        let guide = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../docs/writing-a-driver.md"
        ))
        .expect("docs/writing-a-driver.md");
        let source = include_str!("max31855.rs");
        let mut quoted = 0;
        let mut rest = guide.as_str();
        while let Some(start) = rest.find("```rust\n") {
            let body = &rest[start + 8..];
            let end = body.find("```").expect("closed code block");
            let block = &body[..end];
            assert!(
                source.contains(block),
                "the guide's block is not in src/max31855.rs:\n{block}"
            );
            quoted += 1;
            rest = &body[end + 3..];
        }
        assert!(quoted >= 3, "the guide quotes the driver ({quoted} blocks)");
    }
}
