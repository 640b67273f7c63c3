//! Logical devices over the sim card: the conformance kit's axis check, homing against a
//! position switch, the drive's order of writes when disabled, and sensors in their unit.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::channel::{AnalogInput, AnalogOutput, DigitalInput, DigitalOutput};
use device_interface::conformance::{AxisRig, check_axis};
use device_interface::logical::{
    AnalogDrive, AnalogDriveParts, AnalogSensor, Axis, AxisFault, AxisState, Drive, EncoderSensor,
    HomingConfig, Sensor, ServoAxis, ServoAxisParts,
};
use device_interface::time::{SimClock, Timestamp};
use device_interface::{DeviceError, Registry};
use driver_sim::{OutputWrite, SimCard, SimConfig, SimFault};
use std::sync::Arc;
use std::time::Duration;

/// A card with an axis: analog output 1 is the velocity (1000 counts/s per volt) of
/// encoder 0, digital output 0 the drive's enable, input 8 a home switch 50–60 mm along
/// (100 counts/mm), inputs 9 and 10 free for limit switches a test sets.
const CARD: &str = r#"
digital_inputs = 16
digital_outputs = 8
digital_loopback = true
record_capacity = 4096

[[analog_in]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }
waveform = { kind = "constant", value = 2.0 }

[[analog_out]]
count = 2
range = { lowest = -10.0, highest = 10.0, unit = "V" }

[[encoder]]
resolution = 4096
velocity_from = 1
counts_per_unit = 1000.0

[[switch]]
digital_in = 8
encoder = 0
from = 5000
to = 6000
"#;

const CYCLE: Duration = Duration::from_millis(10);

struct Bench {
    clock: Arc<SimClock>,
    card: Arc<SimCard>,
    registry: Registry,
}

impl Bench {
    fn new() -> Bench {
        let config: SimConfig = toml::from_str(CARD).unwrap();
        let clock = Arc::new(SimClock::new(Timestamp::ZERO));
        let card = SimCard::new(&config, clock.clone()).unwrap();
        let registry = Registry::new();
        card.register(&registry, "sim0").unwrap();
        Bench {
            clock,
            card,
            registry,
        }
    }

    fn cycle(&self) {
        self.clock.advance(CYCLE);
        self.card.step();
    }

    fn drive(&self) -> Arc<AnalogDrive> {
        let ao = self.registry.analog_out().lookup("sim0").unwrap();
        let dout = self.registry.digital_out().lookup("sim0").unwrap();
        Arc::new(
            AnalogDrive::new(AnalogDriveParts {
                setpoint: AnalogOutput::new(ao, 1).unwrap(),
                volts_per_unit: 0.1,
                offset: 0.0,
                enable: Some(DigitalOutput::new(dout, 0, false).unwrap()),
                fault: None,
                unit: "mm/s".into(),
            })
            .unwrap(),
        )
    }

    fn axis(&self, drive: Arc<AnalogDrive>) -> ServoAxis {
        let di = self.registry.digital_in().lookup("sim0").unwrap();
        let enc = self.registry.encoder().lookup("sim0.encoder0").unwrap();
        ServoAxis::new(ServoAxisParts {
            drive,
            encoder: EncoderSensor::new(enc, 100.0, 0.0, "mm").unwrap(),
            limit_max: Some(DigitalInput::new(di.clone(), 9, false).unwrap()),
            limit_min: Some(DigitalInput::new(di.clone(), 10, false).unwrap()),
            home: Some(DigitalInput::new(di, 8, false).unwrap()),
            homing: Some(HomingConfig {
                velocity: 5.0,
                position: 0.0,
                back_off: 2.0,
                max_travel: Some(200.0),
            }),
        })
        .unwrap()
    }

    /// An axis as its own thread would have it: stepped.
    fn stepped_axis(&self, drive: Arc<AnalogDrive>) -> ServoAxis {
        let axis = self.axis(drive);
        axis.set_stepping(true);
        axis
    }
}

#[test]
fn the_axis_keeps_the_conformance_kits_contract() {
    let bench = Bench::new();
    let axis = bench.axis(bench.drive());
    let mut cycle = || bench.cycle();
    let mut limit = |high: bool, on: bool| {
        bench
            .card
            .set_digital_in(if high { 9 } else { 10 }, on)
            .unwrap();
    };
    let dout = bench.registry.digital_out().lookup("sim0").unwrap();
    let enabled = || dout.check_bit(0).unwrap();
    let report = check_axis(
        &axis,
        AxisRig {
            cycle: &mut cycle,
            limit: Some(&mut limit),
            enabled: Some(&enabled),
            jog: 5.0,
            // One cycle at the search velocity latching, one backing off.
            tolerance: 2.0 * 5.0 * CYCLE.as_secs_f64(),
            max_cycles: 10_000,
        },
    );
    report.assert_complete();
}

#[test]
fn homing_latches_the_switch_edge_as_the_home_position_and_backs_off() {
    let bench = Bench::new();
    let drive = bench.drive();
    let axis = bench.stepped_axis(drive.clone());
    axis.enable().unwrap();
    axis.home().unwrap();
    let mut cycles = 0;
    while axis.state() == AxisState::Homing {
        bench.cycle();
        axis.step().unwrap();
        cycles += 1;
        assert!(cycles < 10_000, "homing never ended");
    }
    assert_eq!(axis.state(), AxisState::Ready, "fault {:?}", axis.fault());
    assert!(axis.homed());
    assert_eq!(drive.velocity(), 0.0);
    // 50 mm at 5 mm/s is 10 s: 1000 cycles, then 2 mm back.
    assert!((1000..1100).contains(&cycles), "{cycles} cycles");
    // The switch's edge is at 5000 counts of travel: position 0 there, within one cycle
    // of motion (5 mm/s × 10 ms = 0.05 mm = 5 counts).
    let p = axis.position().unwrap();
    assert!((p + 2.0).abs() <= 0.1, "backed off to {p}, expected -2");
    // Walk back onto the switch: its edge reads as 0 within a cycle.
    axis.jog(1.0).unwrap();
    let di = bench.registry.digital_in().lookup("sim0").unwrap();
    while !di.read_bit(8).unwrap() {
        bench.cycle();
        axis.step().unwrap();
    }
    let edge = axis.position().unwrap();
    assert!(edge.abs() <= 0.02, "the switch's edge reads {edge} mm");
    axis.disable().unwrap();
}

#[test]
fn homing_on_the_switch_moves_off_it_first_and_a_limit_stops_homing() {
    let bench = Bench::new();
    let axis = bench.stepped_axis(bench.drive());
    bench.card.move_encoder(0, 5500).unwrap();
    bench.cycle();
    axis.enable().unwrap();
    axis.home().unwrap();
    assert_eq!(
        axis.velocity(),
        -5.0,
        "on the switch: off it first, backwards"
    );
    for _ in 0..20 {
        bench.cycle();
        axis.step().unwrap();
    }
    // The limit in the search direction turns on while homing.
    bench.card.set_digital_in(9, true).unwrap();
    let mut cycles = 0;
    while axis.state() == AxisState::Homing {
        bench.cycle();
        let _ = axis.step();
        cycles += 1;
        assert!(cycles < 10_000);
    }
    assert_eq!(axis.state(), AxisState::Error);
    assert_eq!(axis.fault(), Some(AxisFault::LimitMax));
    assert!(!axis.homed());
    let dout = bench.registry.digital_out().lookup("sim0").unwrap();
    assert!(!dout.check_bit(0).unwrap(), "the drive's enable is off");
    let ao = bench.registry.analog_out().lookup("sim0").unwrap();
    assert!(ao.read_back(1).unwrap().abs() < 1e-3, "zero velocity");
}

#[test]
fn a_search_beyond_max_travel_fails_and_homing_needs_an_enabled_axis() {
    let bench = Bench::new();
    let axis = bench.stepped_axis(bench.drive());
    assert!(matches!(axis.home(), Err(DeviceError::Refused { .. })));
    bench.card.move_encoder(0, 7000).unwrap(); // past the switch: the search never meets it
    axis.enable().unwrap();
    axis.home().unwrap();
    while axis.state() == AxisState::Homing {
        bench.cycle();
        axis.step().unwrap();
    }
    assert_eq!(axis.fault(), Some(AxisFault::HomeNotFound));
    assert!(axis.position().unwrap() > 200.0 + 70.0 - 1.0);
}

#[test]
fn disabling_writes_zero_velocity_before_the_enable_goes_off() {
    let bench = Bench::new();
    let drive = bench.drive();
    assert!(matches!(
        drive.set_velocity(1.0),
        Err(DeviceError::Refused { .. })
    ));
    drive.enable().unwrap();
    drive.set_velocity(20.0).unwrap();
    assert!(matches!(
        drive.set_velocity(101.0),
        Err(DeviceError::ValueOutOfRange { .. })
    ));
    assert_eq!(drive.velocity(), 20.0);
    assert_eq!(drive.velocity_range().unwrap(), (-100.0, 100.0));
    bench.card.take_output_record();
    drive.disable().unwrap();
    let writes: Vec<_> = bench
        .card
        .take_output_record()
        .into_iter()
        .map(|e| e.write)
        .collect();
    let zero = bench
        .registry
        .analog_out()
        .lookup("sim0")
        .unwrap()
        .scale(1)
        .unwrap()
        .to_raw_saturating(0.0);
    assert_eq!(
        writes,
        [
            OutputWrite::Analog {
                channel: 1,
                raw: zero
            },
            OutputWrite::Bit {
                bit: 0,
                value: false
            }
        ]
    );
    assert!(!drive.is_enabled());
}

#[test]
fn sensors_read_in_their_unit() {
    let bench = Bench::new();
    let ai = bench.registry.analog_in().lookup("sim0").unwrap();
    let pressure = AnalogSensor::new(AnalogInput::new(ai, 0).unwrap(), 25.0, -50.0, "bar").unwrap();
    assert!((pressure.read().unwrap() - 0.0).abs() < 25.0 * 20.0 / 65535.0);
    assert_eq!(pressure.measurement_range(), (-300.0, 200.0));
    assert_eq!(pressure.unit(), "bar");
    let enc = bench.registry.encoder().lookup("sim0.encoder0").unwrap();
    let length = EncoderSensor::new(enc, -100.0, 10.0, "mm").unwrap();
    bench.card.move_encoder(0, 4096 * 3 + 50).unwrap();
    assert_eq!(length.count().unwrap(), 4096 * 3 + 50);
    assert_eq!(length.read().unwrap(), 10.0 - (4096.0 * 3.0 + 50.0) / 100.0);
    assert!(
        EncoderSensor::new(
            bench.registry.encoder().lookup("sim0.encoder0").unwrap(),
            0.0,
            0.0,
            ""
        )
        .is_err()
    );
}

#[test]
fn switches_are_checked_against_the_card() {
    let bad = |extra: &str| {
        let config: SimConfig = toml::from_str(&format!("{CARD}{extra}")).unwrap();
        SimCard::new(&config, Arc::new(SimClock::new(Timestamp::ZERO)))
            .err()
            .map(|e| e.to_string())
    };
    assert_eq!(
        bad("[[switch]]\ndigital_in = 3\nencoder = 0\nfrom = 0\nto = 1\n").as_deref(),
        Some(
            "switch[1].digital_in: digital input 3 is driven by digital_loopback; a switch needs an input no loopback drives"
        )
    );
    assert_eq!(
        bad("[[switch]]\ndigital_in = 8\nencoder = 0\nfrom = 0\nto = 1\n").as_deref(),
        Some("switch[1].digital_in: digital input 8 is switched by switch[0] already")
    );
    assert_eq!(
        bad("[[switch]]\ndigital_in = 11\nencoder = 1\nfrom = 0\nto = 1\n").as_deref(),
        Some("switch[1].encoder: encoder 1 does not exist (the card has 1)")
    );
    assert_eq!(
        bad("[[switch]]\ndigital_in = 11\nencoder = 0\nfrom = 2\nto = 1\n").as_deref(),
        Some("switch[1].to: 1 is below from = 2")
    );
    assert_eq!(
        bad("[[switch]]\ndigital_in = 16\nencoder = 0\nfrom = 0\nto = 1\n").as_deref(),
        Some("switch[1].digital_in: digital input 16 does not exist (the card has 16)")
    );
}

#[test]
fn an_output_changed_under_the_drive_trips_the_axis_instead_of_being_written_over() {
    let bench = Bench::new();
    let axis = bench.stepped_axis(bench.drive());
    axis.enable().unwrap();
    axis.jog(5.0).unwrap();
    bench.cycle();
    axis.step().unwrap();
    // An output watchdog (or anyone) switches the enable off.
    let dout = bench.registry.digital_out().lookup("sim0").unwrap();
    dout.set_bit(0, false).unwrap();
    bench.cycle();
    assert!(matches!(axis.step(), Err(DeviceError::Refused { .. })));
    assert_eq!(axis.state(), AxisState::Error);
    assert_eq!(axis.fault(), Some(AxisFault::Device));
    for _ in 0..5 {
        bench.cycle();
        let _ = axis.step();
    }
    assert!(!dout.check_bit(0).unwrap(), "switched on again");
    assert!(axis.jog(5.0).is_err());
}

#[test]
fn a_disable_that_failed_is_tried_again_every_step() {
    let bench = Bench::new();
    let axis = bench.stepped_axis(bench.drive());
    axis.enable().unwrap();
    axis.jog(5.0).unwrap();
    bench.card.set_fault(SimFault::Offline);
    // The step's reads fail: in error, the drive's disable failing too.
    assert!(axis.step().is_err());
    assert_eq!(axis.state(), AxisState::Error);
    let dout = bench.registry.digital_out().lookup("sim0").unwrap();
    bench.card.set_fault(SimFault::None);
    assert!(
        dout.check_bit(0).unwrap(),
        "the failed disable left the enable on"
    );
    bench.cycle();
    axis.step().unwrap();
    assert!(!dout.check_bit(0).unwrap(), "not retried");
    assert!(axis.reset().is_ok());
    assert_eq!(axis.state(), AxisState::Disabled);
}

#[test]
fn a_home_switch_stuck_on_ends_homing_at_max_travel() {
    let bench = Bench::new();
    let axis = bench.stepped_axis(bench.drive());
    bench.card.set_digital_in(8, true).unwrap();
    bench.cycle();
    axis.enable().unwrap();
    axis.home().unwrap();
    let mut cycles = 0;
    while axis.state() == AxisState::Homing {
        bench.cycle();
        let _ = axis.step();
        cycles += 1;
        assert!(cycles < 10_000, "moving off a stuck switch forever");
    }
    assert_eq!(axis.fault(), Some(AxisFault::HomeNotFound));
    assert!(axis.position().unwrap() < -199.0);
}

#[test]
fn an_axis_no_thread_steps_takes_no_command_that_moves_it() {
    let bench = Bench::new();
    let axis = bench.axis(bench.drive());
    assert!(matches!(axis.enable(), Err(DeviceError::Refused { .. })));
    axis.set_stepping(true);
    axis.enable().unwrap();
    axis.set_stepping(false);
    assert!(matches!(axis.jog(1.0), Err(DeviceError::Refused { .. })));
    assert!(matches!(axis.home(), Err(DeviceError::Refused { .. })));
    axis.disable().unwrap();
}
