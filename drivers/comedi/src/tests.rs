//! The card and its bus side over the in-memory board ([`crate::fake`]): the conformance
//! kit over every interface, what opening writes and in which order, a board that fails,
//! goes away, comes back or comes back as another board, and the section's errors.
#![allow(clippy::unwrap_used, reason = "test code")]

use crate::board::Kind;
use crate::bus::ComediBus;
use crate::card::ComediCard;
use crate::config::ComediConfig;
use crate::fake::{Fake, desc};
use crate::layout::resolve;
use device_interface::conformance;
use device_interface::time::MonotonicClock;
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut};
use std::sync::Arc;
use std::time::{Duration, Instant};

struct Rig {
    fake: Fake,
    card: Arc<ComediCard>,
    bus: ComediBus,
    now: Instant,
}

impl Rig {
    fn new(section: &str) -> Rig {
        let config: ComediConfig =
            toml::from_str(&format!("device = \"/dev/fake\"\n{section}")).unwrap();
        config.check().unwrap();
        let layout = resolve(&config, &desc()).unwrap();
        let card = Arc::new(
            ComediCard::new(
                "/dev/fake",
                "fake board (fake)",
                layout,
                Arc::new(MonotonicClock),
            )
            .unwrap(),
        );
        let fake = Fake::new();
        let bus = ComediBus::new(card.clone(), desc(), fake.opener());
        Rig {
            fake,
            card,
            bus,
            now: Instant::now(),
        }
    }

    /// One poll period later.
    fn step(&mut self) {
        self.now += Duration::from_millis(10);
        self.bus.step(self.now);
    }

    /// Waits out any backoff (6 s of steps).
    fn step_long(&mut self) {
        for _ in 0..600 {
            self.step();
        }
    }

    fn log(&self) -> Vec<String> {
        std::mem::take(&mut self.fake.state().log)
    }
}

const ALL: &str = r#"
analog_in = [{ channels = [0, 1] }, { channels = [2, 3], range = 1, aref = "diff" }]
analog_out = [{ range = 1 }]
input = [{ subdevice = 3 }, { subdevice = 2, channels = [6, 7] }]
output = [{ subdevice = 2, channels = [0, 1, 2, 3] }]
encoder = [{ channel = 1, resolution = 1000 }]
"#;

#[test]
fn conformance_kit_over_every_interface() {
    let mut rig = Rig::new(ALL);
    rig.step();
    assert!(rig.card.is_online(), "{:?}", rig.card.counters());
    rig.step();
    let card = rig.card.clone();
    let fake = rig.fake.clone();
    let rig = std::cell::RefCell::new(rig);
    let mut ai = |ch: u32, raw: i64| {
        let (sub, chan) = [(0, 0), (0, 1), (0, 2), (0, 3)][ch as usize];
        fake.state().data.insert((sub, chan), raw as u32);
        rig.borrow_mut().step();
    };
    conformance::check_analog_in(card.as_ref(), Some(&mut ai)).assert_complete();
    conformance::check_analog_out(card.as_ref()).assert_complete();
    let mut di = |bit: u32, on: bool| {
        let (sub, chan) = [(3, 0), (3, 1), (3, 2), (3, 3), (2, 6), (2, 7)][bit as usize];
        let mut s = fake.state();
        // The DI's levels, the DIO inputs' pins.
        let w = if sub == 2 {
            s.pins.entry(sub)
        } else {
            s.bits.entry(sub)
        }
        .or_default();
        *w = (*w & !(1 << chan)) | (u64::from(on) << chan);
        drop(s);
        rig.borrow_mut().step();
    };
    conformance::check_digital_in(card.as_ref(), Some(&mut di)).assert_complete();
    conformance::check_digital_out(card.as_ref()).assert_complete();
    let enc = card.devices().encoders.into_iter().next().unwrap().1;
    let mut motion = |counts: i64| {
        let mut s = fake.state();
        let c = s.data.entry((4, 1)).or_default();
        *c = (i64::from(*c) + counts).rem_euclid(1 << 24) as u32;
        drop(s);
        rig.borrow_mut().step();
    };
    conformance::check_encoder(enc.as_ref(), Some(&mut motion)).assert_complete();
    // The counter wraps at 2^24 and the encoder counts on across it.
    fake.state().data.insert((4, 1), 0xff_fff0);
    rig.borrow_mut().step();
    let before = enc.position().unwrap() + enc.turn().unwrap() * 1000;
    fake.state().data.insert((4, 1), 0x10);
    rig.borrow_mut().step();
    let after = enc.position().unwrap() + enc.turn().unwrap() * 1000;
    assert_eq!(after - before, 0x20);
}

#[test]
fn opening_writes_nothing_unasked_and_levels_before_directions() {
    let mut rig = Rig::new(ALL);
    rig.fake.state().bits.insert(2, 0b0101);
    // Outputs already (as another program left them): their latch is read, not written.
    rig.fake.state().dirs.insert(2, 0b1111);
    rig.fake.state().data.insert((1, 0), 1234);
    rig.step();
    // Only directions: the outputs' levels were read, not written.
    assert_eq!(
        rig.log(),
        [
            "config 2/0 out",
            "config 2/1 out",
            "config 2/2 out",
            "config 2/3 out",
            "config 2/6 in",
            "config 2/7 in"
        ]
    );
    assert_eq!(rig.card.check_sequence(0, 3).unwrap(), 0b0101);
    assert_eq!(
        rig.card.read_back_raw(0).unwrap(),
        1234,
        "the board's own read-back"
    );
    // With initial values: written first, then the channels made outputs.
    let mut rig = Rig::new(
        "output = [{ subdevice = 2, channels = [0, 1], initial = true }]\nanalog_out = [{ channels = [1], initial = 2.5 }]",
    );
    rig.step();
    assert_eq!(
        rig.log(),
        [
            "bits 2 mask 0x1 = 0x1",
            "bits 2 mask 0x2 = 0x2",
            "config 2/0 out",
            "config 2/1 out",
            "write 1/1 range 0 = 1024",
        ]
    );
}

#[test]
fn writes_go_out_at_once_and_a_sequence_is_one_call() {
    let mut rig = Rig::new(ALL);
    rig.step();
    rig.log();
    rig.card.set_bit(2, true).unwrap();
    rig.card.set_sequence(0, 3, 0b1010).unwrap();
    rig.card.write(1, -10.0).unwrap();
    assert_eq!(
        rig.log(),
        [
            "bits 2 mask 0x4 = 0x4",
            "bits 2 mask 0xf = 0xa",
            "write 1/1 range 1 = 0"
        ]
    );
    assert_eq!(rig.fake.state().bits[&2] & 0xf, 0b1010);
}

#[test]
fn a_board_gone_is_offline_then_opened_again_with_what_was_written() {
    let mut rig = Rig::new(ALL);
    rig.step();
    rig.card.set_bit(1, true).unwrap();
    rig.card.write(0, 5.0).unwrap();
    rig.fake.state().gone = true;
    rig.step();
    assert!(!rig.card.is_online());
    assert!(matches!(rig.card.read_raw(0), Err(DeviceError::Offline)));
    assert!(matches!(
        rig.card.set_bit(0, true),
        Err(DeviceError::Offline)
    ));
    let c = rig.card.counters();
    assert_eq!((c.went_offline, c.opened), (1, 1));
    assert!(c.last_error.unwrap().contains("No such device"));
    // Back, reset, its lines inputs at 0: the one hwgw wrote (bit 1) latched at its level,
    // the others at their pins' (0), before they drive; then AO 0 as written.
    {
        let mut s = rig.fake.state();
        s.gone = false;
        s.bits.clear();
        s.dirs.clear();
        s.data.clear();
        s.log.clear();
    }
    rig.step_long();
    assert!(rig.card.is_online());
    assert_eq!(rig.card.counters().opened, 2);
    assert_eq!(
        rig.log(),
        [
            "bits 2 mask 0x2 = 0x2",
            "bits 2 mask 0xd = 0x0",
            "config 2/0 out",
            "config 2/1 out",
            "config 2/2 out",
            "config 2/3 out",
            "config 2/6 in",
            "config 2/7 in",
            "write 1/0 range 1 = 3071",
        ]
    );
}

#[test]
fn three_failures_in_a_row_take_it_offline_two_do_not() {
    let mut rig = Rig::new("analog_in = [{}]");
    rig.step();
    rig.fake.state().fail = 2;
    rig.step();
    rig.step();
    rig.step();
    assert!(rig.card.is_online());
    assert_eq!(rig.card.counters().errors, 2);
    rig.fake.state().fail = 3;
    for _ in 0..3 {
        rig.step();
    }
    assert!(!rig.card.is_online());
    rig.step_long();
    assert!(rig.card.is_online());
}

#[test]
fn offline_boards_are_tried_with_a_growing_backoff() {
    let mut rig = Rig::new("analog_in = [{}]");
    rig.fake.state().gone = true;
    for _ in 0..1000 {
        rig.step();
    }
    // 10 s of 10 ms steps: 100 ms, 200, 400, 800, 1600, 3200, then every 5 s.
    let tries = rig.card.counters().errors;
    assert!((7..=9).contains(&tries), "{tries} opens tried");
}

#[test]
fn a_subdevice_with_one_direction_refuses_mixed_channels() {
    let mut rig = Rig::new(
        "output = [{ subdevice = 2, channels = [0] }]\ninput = [{ subdevice = 2, channels = [1] }]",
    );
    rig.fake.state().ganged.push(2);
    rig.step();
    assert!(!rig.card.is_online());
    let why = rig.card.counters().last_error.unwrap();
    assert!(
        why.contains("DIO subdevice 2 channel 0 did not stay an output"),
        "{why}"
    );
    assert!(why.contains("channel 1 was made the other"), "{why}");
}

#[test]
fn another_board_in_its_place_is_refused() {
    let mut rig = Rig::new("analog_in = [{}]");
    let mut other = desc();
    other.board = "other board".into();
    other.subdevices.truncate(1);
    rig.fake.state().desc = Some(other);
    rig.step();
    assert!(!rig.card.is_online());
    let why = rig.card.counters().last_error.unwrap();
    assert!(
        why.contains(
            "now other board (fake) with subdevices 0 AI (4 channels), not the fake board"
        ),
        "{why}"
    );
}

#[test]
fn a_range_selected_is_read_from_the_next_poll() {
    let mut rig = Rig::new("analog_in = [{ channels = [0] }]");
    rig.fake.state().data.insert((0, 0), 4095);
    rig.step();
    rig.step();
    assert_eq!(rig.card.read(0).unwrap(), 10.0);
    rig.card.select_range(0, 1).unwrap();
    assert!(matches!(
        rig.card.read_raw(0),
        Err(DeviceError::Stale { .. })
    ));
    rig.step();
    assert_eq!(rig.card.read(0).unwrap(), 5.0);
    assert!(rig.card.select_range(0, 2).is_err());
    assert!(
        rig.card
            .select_reference(0, device_interface::AnalogReference::Common)
            .is_err(),
        "the subdevice has no AREF_COMMON"
    );
}

fn error(section: &str) -> String {
    let config: ComediConfig =
        toml::from_str(&format!("device = \"/dev/fake\"\n{section}")).unwrap();
    match config.check().and_then(|()| resolve(&config, &desc())) {
        Ok(_) => panic!("accepted: {section}"),
        Err(e) => format!("{}: {}", e.key.unwrap_or_default(), e.message),
    }
}

#[test]
fn section_errors_name_the_key_and_what_the_board_has() {
    let cases = [
        ("poll_ms = 0", "poll_ms: 0 is outside 1..=60000"),
        (
            "analog_in = [{ subdevice = 1 }]",
            "analog_in[0].subdevice: subdevice 1 is AO, not AI (the board has: 0 AI (4 channels), 1 AO (2 channels), 2 DIO (8 channels), 3 DI (4 channels), 4 COUNTER (2 channels), 5 DO (48 channels), 6 DI (48 channels))",
        ),
        (
            "analog_in = [{ subdevice = 9 }]",
            "analog_in[0].subdevice: fake board has no subdevice 9",
        ),
        (
            "analog_out = [{ aref = \"diff\" }]",
            "analog_out[0].aref: subdevice 1 does not take aref \"diff\"",
        ),
        (
            "analog_out = [{ initial = 11.0 }]",
            "analog_out[0].initial: 11 is outside range 0 [0, 10]",
        ),
        (
            "input = [{ channels = [4] }]",
            "input[0].channels: subdevice 3 (DI) has no channel 4 (it has 0..=3)",
        ),
        ("input = [{ channels = [] }]", "input[0].channels: is empty"),
        (
            "output = [{ channels = [1, 1] }]",
            "output: subdevice 5 channel 1 is mapped twice",
        ),
        (
            "output = [{ subdevice = 2, channels = [1] }]\ninput = [{ subdevice = 2, channels = [1] }]",
            "output: DIO subdevice 2 channel 1 is an input too",
        ),
        ("encoder = [{ resolution = 0 }]", "encoder[0].resolution"),
        (
            "encoder = [{ channel = 2, resolution = 10 }]",
            "encoder[0].channels: subdevice 4 (COUNTER) has no channel 2",
        ),
    ];
    for (section, want) in cases {
        let got = error(section);
        assert!(got.contains(want), "{section}: {got}");
    }
    // The first subdevice of a kind is the default; DO and DI fall back to DIO.
    let config: ComediConfig =
        toml::from_str("device = \"x\"\noutput = [{}]\ninput = [{}]").unwrap();
    let layout = resolve(&config, &desc()).unwrap();
    assert_eq!((layout.output.len(), layout.output[0].subdevice), (48, 5));
    assert_eq!((layout.input.len(), layout.input[0].subdevice), (4, 3));
    let mut dio_only = desc();
    dio_only.subdevices.truncate(3);
    for (list, section) in [("output", "output = [{}]"), ("input", "input = [{}]")] {
        let config: ComediConfig = toml::from_str(&format!("device = \"x\"\n{section}")).unwrap();
        let layout = resolve(&config, &dio_only).unwrap();
        let chans = if list == "output" {
            &layout.output
        } else {
            &layout.input
        };
        assert_eq!((chans.len(), chans[0].subdevice), (8, 2), "{list}");
    }
    // Both at once would make every DIO channel an input and an output: refused.
    assert!(resolve(&config, &dio_only).is_err());
    assert_eq!(dio_only.subdevices[2].kind, Kind::Dio);
}

#[test]
fn a_dio_input_made_an_output_drives_the_level_its_pin_had() {
    let mut rig = Rig::new("output = [{ subdevice = 2, channels = [0, 1] }]");
    {
        let mut s = rig.fake.state();
        s.pins.insert(2, 0b01);
        s.bits.insert(2, 0b10);
    }
    rig.step();
    assert!(rig.card.is_online());
    // The pins (1, 0) latched before the lines drive, not the stale latch (0, 1).
    assert_eq!(
        rig.log(),
        ["bits 2 mask 0x3 = 0x1", "config 2/0 out", "config 2/1 out"]
    );
    assert_eq!(rig.card.check_sequence(0, 1).unwrap(), 0b01);
}

#[test]
fn a_refused_direction_is_put_back_and_never_tried_again() {
    let mut rig = Rig::new(
        "output = [{ subdevice = 2, channels = [0] }]\ninput = [{ subdevice = 2, channels = [1] }]",
    );
    rig.fake.state().ganged.push(2);
    rig.step();
    assert_eq!(
        rig.fake.state().dirs.get(&2).copied().unwrap_or(0),
        0,
        "inputs as before"
    );
    let calls = rig.fake.state().calls;
    rig.step_long();
    assert_eq!(rig.fake.state().calls, calls, "not opened again");
    assert!(!rig.card.is_online());
}

#[test]
fn after_a_reopen_inputs_are_fresh_and_counters_do_not_jump() {
    let mut rig = Rig::new(
        "analog_in = [{ channels = [0] }]\ninput = [{}]\nencoder = [{ resolution = 100000 }]",
    );
    {
        let mut s = rig.fake.state();
        s.data.insert((0, 0), 100);
        s.data.insert((4, 0), 5000);
        s.bits.insert(3, 1);
    }
    rig.step();
    rig.step();
    let enc = rig.card.devices().encoders.into_iter().next().unwrap().1;
    let at = enc.position().unwrap();
    assert_eq!(
        (rig.card.read_raw(0).unwrap(), rig.card.read_bit(0).unwrap()),
        (100, true)
    );
    rig.fake.state().gone = true;
    rig.step();
    {
        let mut s = rig.fake.state();
        s.gone = false;
        s.data.insert((0, 0), 200);
        s.data.insert((4, 0), 7);
        s.bits.insert(3, 0);
    }
    // The step that opens it polls it: nothing from before the outage is served.
    for _ in 0..600 {
        rig.step();
        if rig.card.is_online() {
            break;
        }
    }
    assert_eq!(
        (rig.card.read_raw(0).unwrap(), rig.card.read_bit(0).unwrap()),
        (200, false)
    );
    // The counter restarted at 7: a new baseline, not a jump of 7 - 5000.
    assert_eq!(enc.position().unwrap(), at);
    rig.fake.state().data.insert((4, 0), 17);
    rig.step();
    assert_eq!(enc.position().unwrap(), at + 10);
}

#[test]
fn after_settle_the_board_is_not_opened_again() {
    let mut rig = Rig::new("analog_out = [{ channels = [0] }]");
    rig.step();
    rig.card.write(0, 5.0).unwrap();
    assert_eq!(rig.card.settle(), Ok(()));
    rig.fake.state().gone = true;
    rig.step();
    rig.fake.state().gone = false;
    rig.step_long();
    assert!(!rig.card.is_online());
    assert!(matches!(
        rig.card.settle(),
        Err(driver_api::SettleError::Offline(_))
    ));
}

#[test]
fn channels_past_31_go_through_their_own_window() {
    let mut rig = Rig::new(
        "output = [{ subdevice = 5, channels = [30, 31, 32, 33, 47] }]\n\
         input = [{ subdevice = 6, channels = [31, 32, 47] }]",
    );
    rig.step();
    assert!(rig.card.is_online(), "{:?}", rig.card.counters());
    rig.log();
    // Channels 30–33 span two windows: one call each, with its base.
    rig.card.set_sequence(0, 3, 0b1011).unwrap();
    rig.card.set_bit(4, true).unwrap();
    assert_eq!(
        rig.log(),
        [
            "bits 5 mask 0xc0000000 = 0xc0000000",
            "bits 5 base 32 mask 0x3 = 0x2",
            "bits 5 base 32 mask 0x8000 = 0x8000",
        ]
    );
    assert_eq!(rig.fake.state().bits[&5], 0b11 << 30 | 1 << 33 | 1 << 47);
    assert_eq!(rig.card.check_sequence(0, 4).unwrap(), 0b11011);
    // Inputs 31, 32 and 47: read in two windows, each bit where it belongs.
    rig.fake.state().bits.insert(6, 1 << 32 | 1 << 47);
    rig.step();
    assert_eq!(rig.card.read_sequence(0, 2).unwrap(), 0b110);
    rig.fake.state().bits.insert(6, 1 << 31);
    rig.step();
    assert_eq!(rig.card.read_sequence(0, 2).unwrap(), 0b001);
}

/// A path that leads to something other than a comedi device is refused from `stat`
/// before comedilib opens it, and named for what it is, comedi loaded or not.
#[test]
fn only_comedi_devices_are_opened() {
    for (path, what) in [
        ("/dev/null", "it is character device 1:3"),
        ("/etc/passwd", "it is a regular file"),
        ("/dev", "it is a directory"),
    ] {
        let Err(e) = crate::board::Board::open(path) else {
            panic!("{path} opened as a comedi board");
        };
        let e = e.to_string();
        assert!(
            e.starts_with(&format!(
                "comedi_open on {path}: not a comedi device: {what} (comedi's are character \
                 devices of major "
            )),
            "{e}"
        );
    }
}
