//! # The simulator's virtual hardware
//!
//! What `stm32f4xx-hal` is to the STM32 board, this crate is to the host simulator board
//! (`forja-sim`): the hardware, behind the `forja-hal-abstraction` and `embedded-hal` traits
//! that the firmware is written against. The board wires it the way the other boards wire
//! theirs; the kernel's and the controller's tests wire their parts to it too, so the firmware
//! is tested on one model of the hardware.
//!
//! ## The hardware
//!
//! One [`SimMachine`] holds the state of a machine described by a TOML machine file
//! ([`config`]); it gives out device handles that implement the hardware traits:
//!
//! | handle | implements | models |
//! |---|---|---|
//! | [`SimClock`] | `Clock` | the virtual clock, `tick_hz` ticks a second (1 MHz by default) |
//! | [`SimAlarm`] | `Alarm` | the one-shot step alarm; the simulation loop fires it |
//! | [`SimStepper`] | `Stepper`, `StepperEnable` | a step/dir driver chip that checks its pulse timing and moves its axis |
//! | [`SimStepDirPins`] | `embedded_hal::digital::OutputPin` ×3 | the same driver's STEP/DIR/ENABLE inputs, for the generic step/dir driver |
//! | [`SimLimitSwitch`] | `LimitSwitch` | an end-stop that trips at a machine position, or the touch probe that closes on the stock's surface |
//! | [`SimSwitchPin`] | `embedded_hal::digital::InputPin` | the same end-stop's or probe's input line, with its polarity |
//! | [`SwitchEdges`] | — | the pin-change interrupt of the switch inputs (an EXTI line on each) |
//! | [`SimHeater`] | `Heater`, `SetDutyCycle` | a heater of a first-order thermal model ([`thermal`]) |
//! | [`SimTemperatureSensor`] | `TemperatureSensor` | that model's temperature, or a sensor fault |
//! | [`SimPwm`] | `SetDutyCycle` | a fan or spindle output that records its duty |
//! | [`SimOutputPin`] | `embedded_hal::digital::OutputPin`, `StatefulOutputPin` | the line of a switched (on/off) output, a coolant valve or a relay, that records when it switched ([`digital`]) |
//! | [`SimBeeper`] | `Beeper` | a buzzer that plays its tones one after another and records them ([`beeper`]) |
//!
//! Devices are named by index in machine-file order (axis 0 is the first `[[axis]]`);
//! [`SimMachine::axis_index`], [`SimMachine::heater_index`], [`SimMachine::output_index`] and
//! [`SimMachine::digital_output_index`] look them up by name. The same handle answers the
//! test's questions: positions in steps, steps lost to a disabled driver, the travel range
//! seen, timing violations, temperatures, duty histories, which outputs are on
//! ([`SimMachine::output_on`]), the tones played, and the step trace ([`trace`]).
//!
//! Besides the machine: [`flash::SimFlash`], a NOR flash (the drivers' in-RAM model, on the
//! heap) whose operations can be written through to a file; the board's two flashes and the
//! state file that keeps them across restarts ([`state`]); its SD card, a directory of the
//! host ([`DirFileStore`], the firmware's `FileStore`: [`files`]); the stores as the firmware
//! uses them, records in the flashes and the card ([`stores::BoardStores`]); the board's
//! static RAM ([`ram::StaticRam`]); and the host links ([`link`]).
//!
//! ## The contract
//!
//! - **Time is virtual.** Nothing moves unless the simulation loop (or a test) advances the
//!   clock: [`SimMachine::advance_to`]. `Clock::now` is the low 32 bits of a 64-bit tick count
//!   that never wraps inside the simulator.
//! - **Execution contexts are kept apart as on hardware.** [`Simulation`] fires the alarm and
//!   calls the firmware's interrupt side ([`Firmware::on_alarm`]), and calls its thread side
//!   ([`Firmware::poll`]) every millisecond of virtual time, interrupt first when both are due.
//!   Neither takes virtual time, so a step pulse's falling edge must be scheduled: a pulse
//!   begun and ended in one interrupt is a timing violation, as it would be on a real driver.
//!   The interrupt may be served late, as on a busy board
//!   ([`SimulationConfig::max_latency_ticks`]).
//! - **Devices never fail** except where a test asks them to (a sensor fault). Their error
//!   types are `Infallible` otherwise.
//! - **Single-threaded.** Handles share the machine through `Rc<RefCell<…>>` and borrow it for
//!   the length of one call.
//!
//! ## Links
//!
//! [`link`] has the host links, each an `embedded-io` byte stream with a connection state
//! ([`link::PortLink`]): [`link::TcpLink`] (like the ESP32's WiFi, one controlling client at a
//! time as the port's session rules decide, `forja_app::session::LinkSession` on the simulator
//! board; default port [`config::DEFAULT_TCP_PORT`]), [`link::WebLink`] (the operator's page
//! over HTTP and the link over its WebSocket, like the ESP32's web server, under the same
//! session rules, a second page watching; default port [`config::DEFAULT_HTTP_PORT`]; its
//! client for tests, [`link::web_client`]), [`link::PtyLink`] (a pseudo-terminal that
//! serial host software opens like a UART), [`link::MemoryLink`] (in-process), and
//! [`link::FaultInjector`], which corrupts and drops bytes from the host at seeded rates.
//!
//! ## The firmware
//!
//! Anything that implements [`Firmware`] runs on the simulated hardware: the simulator board
//! (`forja-sim`) wires the whole firmware to it, a test wires only the parts it tests, as this
//! stand-in for the kernel does. [`Simulation::run_hooked`] gives what stands outside the
//! firmware (a host, a test) a turn after each of its polls.
//!
//! ```
//! use forja_hal_abstraction::clock::{Alarm, Clock};
//! use forja_hal_abstraction::stepper::{Direction, Stepper, StepperEnable};
//! use forja_hal_abstraction::time::{Duration, Instant};
//! use forja_sim_hal::{Firmware, Flow, MachineConfig, SimMachine, SimStepper, Simulation,
//!                     SimulationConfig};
//!
//! /// A stand-in for the kernel: `left` steps at 1 kHz with 5 µs pulses.
//! struct Pulses {
//!     stepper: SimStepper,
//!     left: u32,
//!     high: bool,
//! }
//!
//! impl Firmware for Pulses {
//!     fn on_alarm(&mut self, now: Instant) -> Option<Instant> {
//!         self.high = !self.high;
//!         if self.high {
//!             self.stepper.step_begin().unwrap();
//!             Some(now.wrapping_add(Duration::from_ticks(5)))
//!         } else {
//!             self.stepper.step_end().unwrap();
//!             self.left -= 1;
//!             (self.left > 0).then(|| now.wrapping_add(Duration::from_ticks(995)))
//!         }
//!     }
//!
//!     fn poll(&mut self, _now: Instant) -> Flow {
//!         if self.left == 0 { Flow::Stop } else { Flow::Continue }
//!     }
//! }
//!
//! let machine = SimMachine::new(&MachineConfig::default_router());
//! let x = machine.axis_index('X').unwrap();
//! let mut stepper = machine.stepper(x).unwrap();
//! stepper.set_enabled(true).unwrap();
//! stepper.set_direction(Direction::Positive).unwrap();
//! // First step 10 µs from now: the driver needs 1 µs of DIR set-up.
//! let first = machine.clock().now().wrapping_add(Duration::from_ticks(10));
//! machine.alarm().set_alarm(first).unwrap();
//!
//! let mut firmware = Pulses { stepper, left: 80, high: false };
//! let mut sim = Simulation::new(machine.clone(), SimulationConfig::new(machine.tick_hz()));
//! let report = sim.run(&mut firmware).unwrap();
//! assert_eq!(machine.position_mm(x), Some(151.0)); // from 150 mm, 80 steps of 1/80 mm
//! assert_eq!(machine.violation_count(), 0);
//! assert_eq!(report.alarms, 160);
//! ```
#![deny(unsafe_code)]

pub mod beeper;
pub mod config;
pub mod digital;
pub mod files;
pub mod flash;
pub mod limit;
pub mod link;
pub mod machine;
pub mod pwm;
pub mod ram;
pub mod simulation;
pub mod state;
pub mod stepper;
pub mod stores;
pub mod thermal;
pub mod trace;

pub use beeper::{SimBeeper, Tone};
pub use config::{MachineConfig, MachineFileError};
pub use digital::{OutputChange, SimOutputPin};
pub use files::DirFileStore;
pub use limit::{SimLimitSwitch, SimSwitchPin, SwitchEdges};
pub use machine::{NoSuchDevice, SimAlarm, SimClock, SimMachine};
pub use pwm::{DutyChange, SimPwm};
pub use simulation::{
    Firmware, Flow, FnFirmware, Pacing, RunError, RunReport, Simulation, SimulationConfig,
    StopReason,
};
pub use stepper::{SimDriverPin, SimStepDirPins, SimStepper, TimingViolation, ViolationKind};
pub use thermal::{SensorFault, SimHeater, SimTemperatureSensor};
pub use trace::{StepTrace, TraceEvent, TraceEventKind};
