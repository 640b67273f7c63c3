//! The simulated card against the conformance kit and its own promises: waveforms,
//! loopbacks, encoder motion, faults, the output record, config errors and registration.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::conformance::{self, Rule};
use device_interface::time::{Clock, SimClock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, Device, DeviceError, DigitalIn, DigitalOut, Encoder, Interface, Registry,
    RegistryError, Status,
};
use driver_sim::{OutputWrite, SimCard, SimConfig, SimConfigError, SimFault};
use std::sync::Arc;
use std::time::Duration;

fn clock() -> Arc<SimClock> {
    Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000_000)))
}

fn card_from(toml_text: &str, clock: &Arc<SimClock>) -> Arc<SimCard> {
    let config: SimConfig = toml::from_str(toml_text).unwrap();
    SimCard::new(&config, clock.clone()).unwrap()
}

/// A card wider than one bit-image word, with several analog shapes.
const WIDE: &str = r#"
    seed = 3
    digital_inputs = 70
    digital_outputs = 70
    digital_loopback = true
    record_capacity = 100000

    [[analog_in]]
    count = 2
    range = { lowest = -10.0, highest = 10.0, unit = "V" }
    waveform = { kind = "sine", amplitude = 4.0, frequency = 1.0 }

    [[analog_in]]
    range = { lowest = 4.0, highest = 20.0, unit = "mA" }
    raw = { min = -2048, max = 2047 }
    waveform = { kind = "constant", value = 12.0 }

    [[analog_out]]
    count = 3
    range = { lowest = 0.0, highest = 10.0, unit = "V" }
    raw = { min = 0, max = 4095 }

    [[encoder]]
    resolution = 1024

    [[encoder]]
    resolution = -360
    upcounting = false
"#;

#[test]
fn conformance_every_rule_of_every_interface() {
    let clock = clock();
    let card = card_from(WIDE, &clock);
    let mut set_ai = |c: u32, raw: i64| card.set_analog_in_raw(c, raw).unwrap();
    conformance::check_analog_in(&*card, Some(&mut set_ai)).assert_complete();
    conformance::check_analog_out(&*card).assert_complete();
    let mut set_di = |b: u32, v: bool| card.set_digital_in(b, v).unwrap();
    conformance::check_digital_in(&*card, Some(&mut set_di)).assert_complete();
    conformance::check_digital_out(&*card).assert_complete();
    for i in 0..card.encoder_count() {
        let enc = card.encoder(i).unwrap();
        let mut motion = |n: i64| card.move_encoder(i, n).unwrap();
        conformance::check_encoder(&*enc, Some(&mut motion)).assert_complete();
    }
}

#[test]
fn conformance_of_the_demo_card() {
    // The embedded default must keep the contract too; its inputs move only on step().
    let card = SimCard::new(&SimConfig::demo(), clock()).unwrap();
    let ai = conformance::check_analog_in(&*card, None);
    ai.assert_pass();
    assert_eq!(ai.not_run(), vec![Rule::AiStimulus]);
    conformance::check_analog_out(&*card).assert_complete();
    conformance::check_digital_out(&*card).assert_complete();
    conformance::check_digital_in(&*card, None).assert_pass();
    conformance::check_encoder(&*card.encoder(0).unwrap(), None).assert_pass();
}

#[test]
fn waveforms_at_known_times() {
    let clock = clock();
    let card = card_from(
        r#"
        [[analog_in]]
        range = { lowest = -10.0, highest = 10.0 }
        raw = { min = -1000000, max = 1000000 }
        waveform = { kind = "sine", amplitude = 5.0, frequency = 2.0, offset = 1.0 }
        [[analog_in]]
        range = { lowest = -10.0, highest = 10.0 }
        raw = { min = -1000000, max = 1000000 }
        waveform = { kind = "ramp", from = -4.0, to = 6.0, period = 2.0 }
        [[analog_in]]
        range = { lowest = -1.0, highest = 1.0 }
        waveform = { kind = "constant", value = 0.25 }
        [[analog_in]]
        range = { lowest = -1.0, highest = 1.0 }
        waveform = { kind = "constant", value = 7.0 }
        "#,
        &clock,
    );
    let res = AnalogIn::resolution(&*card, 0).unwrap();
    // t = 0: sine at its offset, ramp at its start, constants; an out-of-range constant
    // saturates like a real converter.
    assert!((card.read(0).unwrap() - 1.0).abs() <= res);
    assert!((card.read(1).unwrap() + 4.0).abs() <= res);
    assert!((card.read(2).unwrap() - 0.25).abs() <= AnalogIn::resolution(&*card, 2).unwrap());
    assert_eq!(card.read(3).unwrap(), 1.0);
    // t = 1/8 s: a quarter period of the 2 Hz sine, the ramp one sixteenth up.
    clock.advance(Duration::from_millis(125));
    card.step();
    assert!((card.read(0).unwrap() - 6.0).abs() <= res);
    assert!((card.read(1).unwrap() - (-4.0 + 10.0 / 16.0)).abs() <= res);
    // t = 2.5 s: the ramp has wrapped to a quarter of its next period.
    clock.advance(Duration::from_millis(2375));
    card.step();
    assert!((card.read(1).unwrap() + 1.5).abs() <= res);
}

#[test]
fn noise_is_seeded_bounded_and_repeatable() {
    let make = |seed: u64| {
        let clock = clock();
        let card = card_from(
            &format!(
                r#"
                seed = {seed}
                [[analog_in]]
                range = {{ lowest = -10.0, highest = 10.0 }}
                raw = {{ min = -1000000, max = 1000000 }}
                waveform = {{ kind = "noise", mean = 2.0, amplitude = 0.5 }}
                "#
            ),
            &clock,
        );
        (0..200)
            .map(|_| {
                clock.advance(Duration::from_millis(1));
                card.step();
                card.read(0).unwrap()
            })
            .collect::<Vec<f64>>()
    };
    let (a, b, c) = (make(1), make(1), make(2));
    assert_eq!(a, b, "the same seed gives the same noise");
    assert_ne!(a, c, "another seed gives other noise");
    assert!(a.iter().all(|v| (1.5..=2.5).contains(v)));
    let mean = a.iter().sum::<f64>() / a.len() as f64;
    assert!((mean - 2.0).abs() < 0.1, "mean {mean}");
    let distinct = a.windows(2).filter(|w| w[0] != w[1]).count();
    assert!(distinct > 190, "noise should change every sample");
}

#[test]
fn analog_and_digital_loopback_happen_at_the_step() {
    let clock = clock();
    let card = SimCard::new(&SimConfig::demo(), clock.clone()).unwrap();
    card.write(0, -3.0).unwrap();
    card.set_bit(2, true).unwrap();
    assert!(
        card.read(3).unwrap().abs() < 1e-3,
        "inputs change only on the card's cycle"
    );
    assert!(!card.read_bit(2).unwrap());
    clock.advance(Duration::from_millis(1));
    card.step();
    assert!((card.read(3).unwrap() + 3.0).abs() <= AnalogIn::resolution(&*card, 3).unwrap());
    assert_eq!(card.read_sequence(0, 7).unwrap(), 0b100);
    // A held input ignores its loopback until released.
    card.set_digital_in(2, false).unwrap();
    card.step();
    assert!(!card.read_bit(2).unwrap());
    card.release_digital_in(2).unwrap();
    card.step();
    assert!(card.read_bit(2).unwrap());
    card.set_analog_in(3, 7.0).unwrap();
    card.step();
    assert!((card.read(3).unwrap() - 7.0).abs() <= AnalogIn::resolution(&*card, 3).unwrap());
    card.release_analog_in(3).unwrap();
    card.step();
    assert!((card.read(3).unwrap() + 3.0).abs() <= AnalogIn::resolution(&*card, 3).unwrap());
}

#[test]
fn encoder_follows_velocity_with_roll_over() {
    let clock = clock();
    let card = card_from(
        r#"
        [[analog_out]]
        range = { lowest = -10.0, highest = 10.0, unit = "V" }
        raw = { min = -10000, max = 10000 }
        [[encoder]]
        resolution = 1024
        velocity_from = 0
        counts_per_unit = 1000.0
        "#,
        &clock,
    );
    let enc = card.encoder(0).unwrap();
    card.write(0, 2.0).unwrap(); // 2000 counts/s
    for _ in 0..1500 {
        clock.advance(Duration::from_millis(1));
        card.step();
    }
    // 3000 counts: 2 turns of 1024 and 952.
    assert_eq!((enc.position().unwrap(), enc.turn().unwrap()), (952, 2));
    // Fractions of a count carry over: 1/3 count per ms for 3 ms is exactly one count.
    card.write(0, 1.0 / 3.0).unwrap();
    let before = 3000;
    for _ in 0..3000 {
        clock.advance(Duration::from_millis(1));
        card.step();
    }
    let total = enc.turn().unwrap() * 1024 + enc.position().unwrap();
    assert!(
        (total - before - 1000).abs() <= 1,
        "moved {}",
        total - before
    );
    // Negative velocity runs backwards through 0 and takes turns off.
    card.write(0, -10.0).unwrap();
    for _ in 0..500 {
        clock.advance(Duration::from_millis(1));
        card.step();
    }
    assert!(enc.turn().unwrap() < 0);
}

#[test]
fn faults_are_errors_with_status_and_recover() {
    let clock = clock();
    let card = SimCard::new(&SimConfig::demo(), clock.clone()).unwrap();
    let enc = card.encoder(0).unwrap();
    card.write(1, 1.0).unwrap();
    assert_eq!(card.health().status, Status::Online);

    card.set_fault(SimFault::Stale);
    clock.advance(Duration::from_millis(250));
    card.step();
    match card.read(0) {
        Err(DeviceError::Stale { age: Some(age) }) => assert_eq!(age, Duration::from_millis(250)),
        other => panic!("expected stale with age, got {other:?}"),
    }
    assert!(matches!(card.read_bit(0), Err(DeviceError::Stale { .. })));
    assert!(matches!(enc.position(), Err(DeviceError::Stale { .. })));
    card.write(1, 2.0)
        .expect("outputs of a stale card still work");
    let h = card.health();
    assert_eq!(h.status, Status::Stale);
    assert_eq!(h.age(), Some(Duration::from_millis(250)));

    card.set_fault(SimFault::Offline);
    assert!(matches!(card.read(0), Err(DeviceError::Offline)));
    assert!(matches!(card.write(1, 5.0), Err(DeviceError::Offline)));
    assert!(matches!(card.set_bit(0, true), Err(DeviceError::Offline)));
    assert!(matches!(
        card.set_sequence(0, 3, 5),
        Err(DeviceError::Offline)
    ));
    assert!(matches!(enc.set_position(1), Err(DeviceError::Offline)));
    assert_eq!(
        AnalogOut::read_back(&*card, 1).unwrap(),
        2.0,
        "a refused write changes nothing"
    );
    assert!(!card.check_bit(0).unwrap());
    assert_eq!(card.health().status, Status::Offline);

    card.set_fault(SimFault::Bus("CRC error on frame 0x123".into()));
    let e = card.read_raw(2).unwrap_err();
    assert_eq!(e.to_string(), "bus error: CRC error on frame 0x123");
    let h = card.health();
    assert_eq!(h.status, Status::Offline);
    assert!(h.last_error.unwrap().to_string().contains("CRC error"));

    card.set_fault(SimFault::None);
    clock.advance(Duration::from_millis(1));
    card.step();
    card.read(0).unwrap();
    let h = card.health();
    assert_eq!((h.status, h.age()), (Status::Online, Some(Duration::ZERO)));
}

#[test]
fn output_record_is_complete_and_ordered() {
    let clock = clock();
    let card = card_from(WIDE, &clock);
    card.set_bit(1, true).unwrap();
    clock.advance(Duration::from_micros(10));
    card.write_raw(2, 77).unwrap();
    card.set_sequence(3, 5, 0b101).unwrap();
    assert!(
        card.set_sequence(3, 5, 0b1000).is_err(),
        "refused writes are not recorded"
    );
    card.encoder(1).unwrap().set_turn(-4).unwrap();
    let rec = card.take_output_record();
    let writes: Vec<OutputWrite> = rec.iter().map(|e| e.write).collect();
    assert_eq!(
        writes,
        vec![
            OutputWrite::Bit {
                bit: 1,
                value: true
            },
            OutputWrite::Analog {
                channel: 2,
                raw: 77
            },
            OutputWrite::Sequence {
                start: 3,
                stop: 5,
                value: 0b101
            },
            OutputWrite::EncoderTurn {
                encoder: 1,
                turn: -4
            },
        ]
    );
    assert_eq!(
        rec.iter().map(|e| e.seq).collect::<Vec<_>>(),
        vec![0, 1, 2, 3]
    );
    assert!(rec[1].time > rec[0].time);
    assert!(
        card.take_output_record().is_empty(),
        "taking empties the record"
    );

    // Two threads writing at once: every write is there, in a per-thread order that matches.
    let writers: Vec<_> = (0..2u32)
        .map(|t| {
            let card = card.clone();
            std::thread::spawn(move || {
                for i in 0..5000u32 {
                    card.set_bit(10 + t, i % 2 == 0).unwrap();
                }
            })
        })
        .collect();
    for w in writers {
        w.join().unwrap();
    }
    let rec = card.take_output_record();
    assert_eq!(rec.len(), 10000);
    assert!(rec.windows(2).all(|w| w[0].seq < w[1].seq));
    for t in 0..2u32 {
        let values: Vec<bool> = rec
            .iter()
            .filter_map(|e| match e.write {
                OutputWrite::Bit { bit, value } if bit == 10 + t => Some(value),
                _ => None,
            })
            .collect();
        assert_eq!(values.len(), 5000);
        assert!(values.iter().enumerate().all(|(i, v)| *v == (i % 2 == 0)));
    }
    assert_eq!(card.output_record_dropped(), 0);
}

#[test]
fn a_full_record_drops_and_counts_but_outputs_still_change() {
    let clock = clock();
    let card = card_from("digital_outputs = 4\nrecord_capacity = 3", &clock);
    for i in 0..5 {
        card.set_bit(0, i % 2 == 0).unwrap();
    }
    assert!(card.check_bit(0).unwrap());
    assert_eq!(card.take_output_record().len(), 3);
    assert_eq!(card.output_record_dropped(), 2);
}

#[test]
fn bad_configs_name_the_key() {
    let cases: &[(&str, &str)] = &[
        (
            "[[analog_in]]\nrange = { lowest = 1.0, highest = 1.0 }\nwaveform = { kind = \"constant\", value = 1.0 }",
            "analog_in[0].range: physical range [1, 1] is invalid: needs finite lowest < highest",
        ),
        (
            "[[analog_out]]\nrange = { lowest = 0.0, highest = 1.0 }\n[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"loopback\", analog_out = 4 }",
            "analog_in[0].waveform.analog_out: analog output 4 does not exist (the card has 1 analog outputs)",
        ),
        (
            "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"ramp\", from = 0.0, to = 1.0, period = 0.0 }",
            "analog_in[0].waveform.period: 0 s: expected a period > 0",
        ),
        (
            "[[analog_out]]\nrange = { lowest = 0.0, highest = 1.0, unit = \"a-unit-name-that-is-far-too-long\" }",
            "analog_out[0].range: unit \"a-unit-name-that-is-far-too-long\" is longer than 23 bytes",
        ),
        (
            "[[analog_out]]\nrange = { lowest = 0.0, highest = 1.0 }\ninitial = 2.0",
            "analog_out[0].initial: 2 is outside the range",
        ),
        (
            "[[analog_out]]\nrange = { lowest = 0.0, highest = 1.0 }\nraw = { min = 5, max = 5 }",
            "analog_out[0].range: raw range [5, 5] is invalid: min must be below max",
        ),
        (
            "[[encoder]]\nresolution = 0",
            "encoder[0].resolution: 0 is not a resolution",
        ),
        (
            "[[encoder]]\nresolution = 10\nvelocity_from = 0",
            "encoder[0].velocity_from: analog output 0 does not exist (the card has 0 analog outputs)",
        ),
        // Arithmetic that would overflow: refused, not saturated or NaN at run time.
        (
            "[[analog_out]]\nrange = { lowest = -10.0, highest = 10.0 }\n[[encoder]]\nresolution = 4096\nvelocity_from = 0\ncounts_per_unit = 1e308",
            "encoder[0].counts_per_unit: 1e308 counts/s per unit: over the velocity output's range [-10, 10] that is more counts/s than any number",
        ),
        (
            "[[analog_out]]\nrange = { lowest = -10.0, highest = 10.0 }\n[[encoder]]\nresolution = 4096\nvelocity_from = 0\ncounts_per_unit = 1e14",
            "encoder[0].counts_per_unit: 100000000000000 counts/s per unit: over the velocity output's range [-10, 10] that is up to 1e15 counts/s; an encoder counts at most 106751991167300 counts/s",
        ),
        (
            "[[encoder]]\nresolution = 4096\ncounts_per_unit = nan",
            "encoder[0].counts_per_unit: is NaN: give a finite number",
        ),
        (
            "[[analog_in]]\nrange = { lowest = -1.7e308, highest = 1.7e308 }\nwaveform = { kind = \"constant\", value = 1.0 }",
            "analog_in[0].range: physical range [-1.7e308, 1.7e308] is too wide",
        ),
        (
            "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"sine\", amplitude = 1e308, offset = 1e308, frequency = 1.0 }",
            "analog_in[0].waveform.amplitude: |offset| + |amplitude| overflows",
        ),
        (
            "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"noise\", mean = -1e308, amplitude = 1e308 }",
            "analog_in[0].waveform.amplitude: |mean| + |amplitude| overflows",
        ),
        (
            "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"sine\", amplitude = 1.0, frequency = 1e308 }",
            "analog_in[0].waveform.frequency: 2π × frequency overflows",
        ),
    ];
    for (text, want) in cases {
        let config: SimConfig = toml::from_str(text).unwrap();
        let err: SimConfigError = match SimCard::new(&config, clock()) {
            Err(e) => e,
            Ok(_) => panic!("{text}: accepted"),
        };
        assert!(err.to_string().starts_with(want), "got {err}\nwant {want}");
    }
}

#[test]
fn unknown_keys_are_refused_by_the_config_parser() {
    for text in [
        "digital_input = 8",
        "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"sine\", amplitude = 1.0, frequency = 1.0, frequncy = 2.0 }",
        "[[analog_in]]\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"square\" }",
        "[[encoder]]\nresolution = 10\nspeed = 3",
    ] {
        let err = toml::from_str::<SimConfig>(text).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("unknown"), "{text}: {msg}");
    }
}

#[test]
fn registers_every_interface_and_rolls_back_on_conflict() {
    let registry = Registry::new();
    let clock = clock();
    let card = SimCard::new(&SimConfig::demo(), clock.clone()).unwrap();
    card.register(&registry, "rack1/sim").unwrap();
    let names: Vec<(Interface, String)> = registry
        .entries()
        .into_iter()
        .map(|e| (e.interface, e.info.name))
        .collect();
    assert_eq!(
        names,
        vec![
            (Interface::AnalogIn, "rack1/sim".to_string()),
            (Interface::AnalogOut, "rack1/sim".to_string()),
            (Interface::DigitalIn, "rack1/sim".to_string()),
            (Interface::DigitalOut, "rack1/sim".to_string()),
            (Interface::Encoder, "rack1/sim.encoder0".to_string()),
        ]
    );
    // The same object under several interfaces.
    registry
        .digital_out()
        .lookup("rack1/sim")
        .unwrap()
        .switch_on(0)
        .unwrap();
    clock.advance(Duration::from_millis(1));
    card.step();
    assert!(
        registry
            .digital_in()
            .lookup("rack1/sim")
            .unwrap()
            .is_on(0)
            .unwrap()
    );

    // A second card whose encoder name is taken: the error names both owners, and the
    // second card leaves nothing behind.
    registry
        .encoder()
        .register("other.encoder0", "elsewhere", card.encoder(0).unwrap())
        .unwrap();
    let other = SimCard::new(&SimConfig::demo(), clock).unwrap();
    let err = other.register(&registry, "other").unwrap_err();
    assert_eq!(
        err,
        RegistryError::Duplicate {
            interface: Interface::Encoder,
            name: "other.encoder0".into(),
            existing_owner: "elsewhere".into(),
            new_owner: "other".into(),
        }
    );
    assert!(registry.analog_in().get("other").is_none());
    assert!(
        registry.encoder().get("other.encoder0").is_some(),
        "the holder keeps its name"
    );
    // A card going away takes all its names with it.
    assert_eq!(registry.unregister_owner("rack1/sim").len(), 5);
}

#[test]
fn the_card_clock_drives_health_ages() {
    let clock = clock();
    let card = SimCard::new(&SimConfig::demo(), clock.clone()).unwrap();
    let t0 = clock.now();
    clock.advance(Duration::from_secs(3));
    let h = card.health();
    assert_eq!(h.last_good, Some(t0));
    assert_eq!(h.age(), Some(Duration::from_secs(3)));
}
