//! The simulator board's description of its parts: its pin map and its machine, as a firmware
//! board's `src/board/` holds them, read from the machine file.
//!
//! | part | on the simulator |
//! |---|---|
//! | motor drivers | each axis's simulated driver chip ([`SimStepDirPins`]) with the timing the machine file gives it |
//! | limit inputs | each homing axis's homing switch ([`AxisConfig::homing_switch`](forja_sim_hal::config::AxisConfig::homing_switch)), read with its polarity; other switches of the file (a hard limit at the far end) are modelled but not wired |
//! | probe input | the machine file's `[probe]`, if any ([`SimMachine::probe_pin`]), read with its polarity like a limit input: `G38.2`–`G38.5` |
//! | heaters | the hot end and the bed ([`MachineConfig::hot_end_heater`], [`MachineConfig::bed_heater`]): a simulated heater and its sensor, under PID control with Marlin's default gains |
//! | PWM outputs | the spindle ([`MachineConfig::spindle_output`], [`SPINDLE_MAX_RPM`] at full duty), the fans 0, 1, … ([`MachineConfig::fan_outputs`], at most [`MAX_FANS`]) |
//! | coolant | the machine file's digital outputs `flood` and `mist`, those it has ([`MachineConfig::flood_output`], [`MachineConfig::mist_output`]): `Output`s on their lines ([`SimOutputPin`]) with the file's active level, one `Coolant` over them ([`CoolantLines::into_coolant`]): `M7`, `M8`, `M9`, grbl's `0xA0`/`0xA1`; other digital outputs are modelled but not wired |
//! | beeper | the machine file's `[beeper]`, if any ([`SimBeeper`]): `M300` |
//! | machine | [`machine`]: the machine file's axes for the kernel, the homing switches numbered in axis order and the probe after them, `Z` homing first and the others in file order, axes without travel limits (rotary, extruder) given ±[`UNLIMITED_TRAVEL_MM`] |
//! | controller | [`controller`]: a `printer` when the file has heaters, else a `cnc`; one extruder when an axis is one; the steps scheduled for the slowest driver; heaters within [`HEATER_TOLERANCE_MC`] of their target for `M109`/`M116` |

use forja_app::controller::ControllerConfig;
use forja_drivers::coolant::Coolant;
use forja_drivers::heater::{HeaterConfig, PidGains};
use forja_drivers::limit::{LimitConfig, LimitInput};
use forja_drivers::output::Output;
use forja_drivers::pwm::SpindleConfig;
use forja_drivers::stepper::StepDirConfig;
use forja_hal_abstraction::device::CoolantControl;
use forja_hal_abstraction::stepper::Direction;
use forja_motion::{AxisConfig, AxisKind as KernelAxisKind, HomeDirection, HomingConfig};
use forja_sim_hal::config::{AxisKind, MachineConfig};
use forja_sim_hal::{SimBeeper, SimHeater, SimMachine, SimPwm, SimStepDirPins, SimSwitchPin};
use forja_sim_hal::{SimOutputPin, SimTemperatureSensor, machine::NoSuchDevice};

use super::BoardError;

/// The spindle's speed at full duty, rpm.
pub const SPINDLE_MAX_RPM: u32 = 24_000;

/// Fans the board drives at most (outputs beyond are not wired).
pub const MAX_FANS: usize = 4;

/// Travel given to an axis the machine file leaves unlimited, mm either side of 0.
pub const UNLIMITED_TRAVEL_MM: f32 = 100_000.0;

/// How close to its target a heater must be for `M109`/`M116` to go on, millidegrees.
pub const HEATER_TOLERANCE_MC: i32 = 2_000;

/// PID gains of the hot end (Marlin's defaults, in fractions of full power).
const HOT_END_GAINS: PidGains = PidGains {
    kp: 0.087,
    ki: 0.0042,
    kd: 0.45,
};

/// PID gains of the bed (Marlin's defaults, in fractions of full power).
const BED_GAINS: PidGains = PidGains {
    kp: 0.39,
    ki: 0.002,
    kd: 4.0,
};

/// A heater of the machine: its sensor, its output and how it is controlled.
#[derive(Debug)]
pub struct HeaterPins {
    /// The temperature sensor.
    pub sensor: SimTemperatureSensor,
    /// The heater's output.
    pub heater: SimHeater,
    /// Its control loop.
    pub config: HeaterConfig,
}

/// The coolant lines of a machine, each an `Output` with its active level; `None` where the
/// machine file has no such digital output.
#[derive(Debug)]
pub struct CoolantLines {
    /// The mist line (`M7`): the digital output `mist`.
    pub mist: Option<Output<SimOutputPin>>,
    /// The flood line (`M8`): the digital output `flood`.
    pub flood: Option<Output<SimOutputPin>>,
}

impl CoolantLines {
    /// The coolant over the lines the machine has, as the controller takes it (a `dyn`: the
    /// driver's type depends on which lines there are); `None` for a machine with neither.
    pub fn into_coolant(self) -> Option<Box<dyn CoolantControl>> {
        match (self.mist, self.flood) {
            (Some(mist), Some(flood)) => Some(Box::new(Coolant::mist_and_flood(mist, flood))),
            (Some(mist), None) => Some(Box::new(Coolant::mist(mist))),
            (None, Some(flood)) => Some(Box::new(Coolant::flood(flood))),
            (None, None) => None,
        }
    }
}

/// The devices of a machine of `N` axes, as the firmware's parts use them.
#[derive(Debug)]
pub struct Pins<const N: usize> {
    /// Each axis's driver chip inputs and their timing.
    pub drivers: [(SimStepDirPins, StepDirConfig); N],
    /// Each axis's homing switch input and how it reads; `None` for an axis that does not
    /// home.
    pub homing_switches: [Option<(SimSwitchPin, LimitConfig)>; N],
    /// The touch probe's input and how it reads, if the machine has one.
    pub probe: Option<(SimSwitchPin, LimitConfig)>,
    /// The hot end, if the machine has one.
    pub hot_end: Option<HeaterPins>,
    /// The bed, if the machine has one.
    pub bed: Option<HeaterPins>,
    /// The fans' outputs, by `M106` `P` index.
    pub fans: [Option<SimPwm>; MAX_FANS],
    /// The spindle's output and its speed range, if the machine has one.
    pub spindle: Option<(SimPwm, SpindleConfig)>,
    /// The coolant lines, those the machine has.
    pub coolant: CoolantLines,
    /// The beeper, if the machine has one.
    pub beeper: Option<SimBeeper>,
}

/// The devices of `machine` as the firmware's parts. See the [module documentation](self).
///
/// Errors: [`BoardError::AxisCount`] unless the machine has `N` axes.
pub fn pins<const N: usize>(machine: &SimMachine) -> Result<Pins<N>, BoardError> {
    let file = machine.config();
    let count = || BoardError::AxisCount(file.axes.len());
    if file.axes.len() != N {
        return Err(count());
    }
    let device = |e: NoSuchDevice| BoardError::Storage(e.to_string());
    let drivers: Vec<_> = file
        .axes
        .iter()
        .enumerate()
        .map(|(i, a)| Ok((machine.step_dir_pins(i)?, StepDirConfig::new(a.step_timing))))
        .collect::<Result<_, NoSuchDevice>>()
        .map_err(device)?;
    let homing_switches = core::array::from_fn(|i| {
        let switch = file.axes.get(i)?.homing_switch()?;
        let pin = machine.switch_pin(i, switch.side).ok()?;
        Some((pin, LimitConfig::new(switch.polarity.into(), 1)))
    });
    let heater = |i: Option<usize>, config| -> Option<HeaterPins> {
        let i = i?;
        Some(HeaterPins {
            sensor: machine.temperature_sensor(i).ok()?,
            heater: machine.heater(i).ok()?,
            config,
        })
    };
    // Switched off as it is made (`Output::new`); the simulated line never refuses a write.
    let line = |i: Option<usize>| -> Option<Output<SimOutputPin>> {
        let i = i?;
        let active = file.digital_outputs.get(i)?.active;
        Output::new(machine.digital_output(i).ok()?, active).ok()
    };
    let mut fans: [Option<SimPwm>; MAX_FANS] = Default::default();
    for (slot, i) in fans.iter_mut().zip(file.fan_outputs()) {
        *slot = machine.pwm(i).ok();
    }
    Ok(Pins {
        drivers: drivers.try_into().map_err(|_| count())?,
        homing_switches,
        probe: file.probe.and_then(|p| {
            Some((
                machine.probe_pin().ok()?,
                LimitConfig::new(p.polarity.into(), 1),
            ))
        }),
        hot_end: heater(file.hot_end_heater(), HeaterConfig::hot_end(HOT_END_GAINS)),
        bed: heater(file.bed_heater(), HeaterConfig::bed(BED_GAINS)),
        fans,
        spindle: file
            .spindle_output()
            .and_then(|i| machine.pwm(i).ok())
            .map(|pwm| (pwm, SpindleConfig::new(SPINDLE_MAX_RPM))),
        coolant: CoolantLines {
            mist: line(file.mist_output()),
            flood: line(file.flood_output()),
        },
        beeper: machine.beeper().ok(),
    })
}

/// A switch input of [`Pins`] as the firmware reads it: a `LimitInput` with its polarity.
pub fn limit_input(
    switch: &Option<(SimSwitchPin, LimitConfig)>,
) -> Option<LimitInput<SimSwitchPin>> {
    switch
        .clone()
        .map(|(pin, config)| LimitInput::new(pin, config))
}

/// The switches the step interrupt reads, in the order [`machine`] numbers them: the homing
/// switches (`homing`, [`Pins::homing_switches`]) in axis order, then the probe (`probe`,
/// [`Pins::probe`]).
pub fn step_switches(
    homing: &[Option<(SimSwitchPin, LimitConfig)>],
    probe: &Option<(SimSwitchPin, LimitConfig)>,
) -> Vec<LimitInput<SimSwitchPin>> {
    homing
        .iter()
        .chain([probe])
        .filter_map(limit_input)
        .collect()
}

/// The kernel's machine for a machine file of `N` axes, before the stored settings are
/// applied over it. See the [module documentation](self) for how switches, the probe,
/// unlimited axes and the homing order are mapped: the switches are numbered as the step
/// interrupt is given them, the homing switches of [`Pins::homing_switches`] in axis order,
/// then [`Pins::probe`].
///
/// Errors: [`BoardError::AxisCount`] unless the file has `N` axes; [`BoardError::Config`] for
/// a machine the kernel refuses.
pub fn machine<const N: usize>(
    m: &MachineConfig,
) -> Result<forja_motion::MachineConfig<N>, BoardError> {
    if m.axes.len() != N {
        return Err(BoardError::AxisCount(m.axes.len()));
    }
    let mut switch = 0u8;
    let axes = core::array::from_fn(|i| {
        let a = &m.axes[i];
        let (min_mm, max_mm) = a
            .travel
            .map_or((-UNLIMITED_TRAVEL_MM, UNLIMITED_TRAVEL_MM), |t| {
                (t.min_mm as f32, t.max_mm as f32)
            });
        let homing = a.homing.map(|h| {
            let c = HomingConfig {
                direction: match h.direction {
                    Direction::Negative => HomeDirection::Min,
                    Direction::Positive => HomeDirection::Max,
                },
                seek_mm_min: h.seek_mm_min as f32,
                locate_mm_min: h.locate_mm_min as f32,
                pull_off_mm: h.pull_off_mm as f32,
                switch,
                order: u8::from(a.letter != 'Z'),
            };
            switch += 1;
            c
        });
        AxisConfig {
            letter: a.letter as u8,
            kind: match a.kind {
                AxisKind::Linear => KernelAxisKind::Linear,
                AxisKind::Rotary => KernelAxisKind::Rotary,
                AxisKind::Extruder => KernelAxisKind::Extruder,
            },
            steps_per_mm: a.steps_per_mm as f32,
            max_rate_mm_min: a.max_rate_mm_min as f32,
            accel_mm_s2: a.accel_mm_s2 as f32,
            min_mm,
            max_mm,
            homing,
        }
    });
    let mut config = forja_motion::MachineConfig::new(axes);
    config.probe_switch = m.probe.map(|_| switch);
    config.validate().map_err(BoardError::Config)?;
    Ok(config)
}

/// The controller's configuration for a machine file. See the
/// [module documentation](self).
pub fn controller(m: &MachineConfig) -> ControllerConfig {
    let kind = if m.heaters.is_empty() {
        "cnc"
    } else {
        "printer"
    };
    let mut config = ControllerConfig::new(kind, m.slowest_step_timing());
    config.extruders = u8::from(m.axes.iter().any(|a| a.kind == AxisKind::Extruder));
    config.heater_tolerance_mc = HEATER_TOLERANCE_MC;
    config
}

#[cfg(test)]
mod tests {
    use forja_drivers::limit::Polarity;
    use forja_hal_abstraction::device::DeviceError;
    use forja_hal_abstraction::limit::LimitSwitch as _;
    use forja_hal_abstraction::stepper::StepTiming;

    use super::*;

    #[test]
    fn the_router_file_makes_a_kernel_configuration() {
        let file = MachineConfig::default_router();
        let k = machine::<4>(&file).unwrap();
        let letters: Vec<u8> = k.axes.iter().map(|a| a.letter).collect();
        assert_eq!(letters, b"XYZA");
        let homing: Vec<_> = k.axes.iter().map(|a| a.homing).collect();
        // Switches numbered in axis order; Z first; A does not home and turns freely.
        assert_eq!(
            homing
                .iter()
                .map(|h| h.map(|h| (h.switch, h.order)))
                .collect::<Vec<_>>(),
            [Some((0, 1)), Some((1, 1)), Some((2, 0)), None]
        );
        assert_eq!(homing[2].map(|h| h.direction), Some(HomeDirection::Max));
        assert_eq!(
            (k.axes[3].min_mm, k.axes[3].max_mm),
            (-100_000.0, 100_000.0)
        );
        assert_eq!(k.axes[3].kind, KernelAxisKind::Rotary);
        assert_eq!(
            k.probe_switch,
            Some(3),
            "the probe after the three homing switches"
        );
        assert_eq!(machine::<3>(&file), Err(BoardError::AxisCount(4)));
        assert_eq!(file.slowest_step_timing(), StepTiming::CONSERVATIVE);
    }

    #[test]
    fn the_routers_coolant_drives_its_flood_and_mist_lines() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let lines = pins::<4>(&m).unwrap().coolant;
        assert!(lines.mist.is_some() && lines.flood.is_some());
        let mut coolant = lines.into_coolant().unwrap();
        coolant.set_flood(true).unwrap();
        assert_eq!(
            (m.output_on("flood"), m.output_on("mist")),
            (Some(true), Some(false))
        );
        coolant.set_mist(true).unwrap();
        coolant.set_flood(false).unwrap();
        assert_eq!(
            (m.output_on("flood"), m.output_on("mist")),
            (Some(false), Some(true))
        );

        // One line only: the other cannot be turned on.
        let text = MachineConfig::bundled_toml("default")
            .unwrap()
            .replace("name = \"mist\"", "name = \"vacuum\"");
        let m = SimMachine::new(&MachineConfig::from_toml_str(&text).unwrap());
        let mut coolant = pins::<4>(&m).unwrap().coolant.into_coolant().unwrap();
        assert_eq!(coolant.set_mist(true), Err(DeviceError::OutOfRange));
        coolant.set_flood(true).unwrap();
        assert_eq!(
            (m.output_on("flood"), m.output_on("vacuum")),
            (Some(true), Some(false))
        );

        let printer =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        let lines = pins::<4>(&SimMachine::new(&printer)).unwrap().coolant;
        assert!(lines.into_coolant().is_none());
    }

    #[test]
    fn a_machine_without_a_probe_has_no_probe_switch() {
        let file =
            MachineConfig::from_toml_str(MachineConfig::bundled_toml("printer").unwrap()).unwrap();
        assert_eq!(machine::<4>(&file).unwrap().probe_switch, None);
        assert!(pins::<4>(&SimMachine::new(&file)).unwrap().probe.is_none());
    }

    #[test]
    fn the_router_has_a_spindle_and_three_homing_switches() {
        let m = SimMachine::new(&MachineConfig::default_router());
        let p = pins::<4>(&m).unwrap();
        assert_eq!(p.homing_switches.iter().flatten().count(), 3);
        assert!(p.homing_switches[3].is_none());
        // The probe: normally open, open at Z 50 mm, touching at Z 20 mm (400 steps/mm).
        assert_eq!(
            p.probe.as_ref().map(|(_, c)| *c),
            Some(LimitConfig::new(Polarity::NormallyOpen, 1))
        );
        // Numbered as the kernel's machine numbers them: the probe is switch 3.
        let mut switches = step_switches(&p.homing_switches, &p.probe);
        assert_eq!(switches.len(), 4);
        assert_eq!(switches[3].is_triggered(), Ok(false));
        m.set_position_steps(2, 20 * 400).unwrap();
        assert_eq!(switches[3].is_triggered(), Ok(true));
        assert_eq!(switches[2].is_triggered(), Ok(false), "Z's homing switch");
        assert!(p.spindle.is_some() && p.hot_end.is_none() && p.bed.is_none());
        assert!(p.beeper.is_none());
        assert!(p.fans.iter().all(Option::is_none));
        assert!(matches!(pins::<3>(&m), Err(BoardError::AxisCount(4))));
        assert_eq!(controller(m.config()).extruders, 0);
    }
}
