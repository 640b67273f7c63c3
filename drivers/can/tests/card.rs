//! The CAN card's device side against the conformance kit, on the host: frames are handed
//! to the card as the bus side would, so every rule runs without a kernel.
#![allow(clippy::unwrap_used, reason = "test code")]

use device_interface::conformance;
use device_interface::time::{Clock, SimClock, Timestamp};
use device_interface::{Device, DeviceError, Status};
use driver_can::card::CanCard;
use driver_can::map::{CanConfig, CanMap, SignalRole};
use std::cell::RefCell;
use std::sync::Arc;
use std::time::Duration;

const CONFIG: &str = r#"
interface = "vcan0"
dbc = "motion.dbc"
[[rx]]
message = "Motion"
cycle_ms = 10
signal = [
    { name = "Mode", as = "digital" },
    { name = "Position", as = "encoder", resolution = 1000 },
]
[[rx]]
message = "Temps"
[[tx]]
message = "Command"
cycle_ms = 10
[[tx]]
id = 0x210
length = 8
signal = [
    { name = "lamps", start = 0, length = 40, as = "digital" },
    { name = "level", start = 40, length = 16, signed = true, factor = 0.25, offset = 1 },
]
[[tx]]
message = "Trims"
fd = true
cycle_ms = 10
"#;

fn card(clock: Arc<SimClock>) -> Arc<CanCard> {
    let config: CanConfig = toml::from_str(CONFIG).unwrap();
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    let card = CanCard::new(CanMap::new(&config, dir.as_ref()).unwrap(), clock);
    card.set_link(true, None);
    card
}

#[test]
fn conformance_every_rule() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000)));
    let card = card(clock.clone());
    let map = card.map().clone();
    // The payload of each rx frame as the peer last sent it.
    let images = RefCell::new(vec![[0u8; 64]; map.rx().len()]);
    let resend = |f: usize| {
        let frame = &map.rx()[f];
        let data = images.borrow()[f];
        card.receive(
            frame.id,
            frame.extended,
            frame.fd,
            &data[..frame.length],
            clock.now(),
        );
    };
    for f in 0..map.rx().len() {
        resend(f);
    }
    let find = |role: SignalRole, ch: u32| {
        map.rx()
            .iter()
            .enumerate()
            .flat_map(|(f, fr)| fr.signals.iter().map(move |s| (f, s)))
            .find(|(_, s)| s.role == role && (s.channel..s.channel + s.width()).contains(&ch))
            .unwrap()
    };
    let mut set_ai = |ch: u32, raw: i64| {
        let (f, s) = find(SignalRole::Analog, ch);
        s.signal.insert(&mut images.borrow_mut()[f], raw).unwrap();
        resend(f);
    };
    // The devices as registered: each a view of the card.
    let devices = card.devices();
    let analog_in = devices.analog_in.clone().unwrap();
    conformance::check_analog_in(&*analog_in, Some(&mut set_ai)).assert_complete();
    let mut set_di = |bit: u32, v: bool| {
        let (f, s) = find(SignalRole::Digital, bit);
        let mut raw = s.signal.extract(&images.borrow()[f]).unwrap();
        let k = bit - s.channel;
        raw = if v { raw | 1 << k } else { raw & !(1 << k) };
        s.signal.insert(&mut images.borrow_mut()[f], raw).unwrap();
        resend(f);
    };
    let digital_in = devices.digital_in.clone().unwrap();
    conformance::check_digital_in(&*digital_in, Some(&mut set_di)).assert_complete();
    conformance::check_analog_out(&*devices.analog_out.clone().unwrap()).assert_complete();
    conformance::check_digital_out(&*devices.digital_out.clone().unwrap()).assert_complete();
    let (f, s) = find(SignalRole::Encoder, 0);
    let mut motion = |n: i64| {
        let raw = s.signal.extract(&images.borrow()[f]).unwrap();
        s.signal
            .insert(&mut images.borrow_mut()[f], (raw + n).rem_euclid(1 << 16))
            .unwrap();
        resend(f);
    };
    conformance::check_encoder(&*devices.encoders[0].1, Some(&mut motion)).assert_complete();
}

#[test]
fn outputs_pack_into_frames_and_staleness_is_per_frame() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000)));
    let card = card(clock.clone());
    use device_interface::{AnalogIn, AnalogOut, DigitalOut};
    // Command: Setpoint (Motorola, signed, 0.1) then Run, Reverse.
    card.write(0, -12.3).unwrap();
    card.set_bit(0, true).unwrap();
    let mut buf = [0u8; 64];
    assert_eq!(card.compose(0, &mut buf), 4);
    assert_eq!(buf[..4], [0xFF, 0x85, 0x01, 0x00]);
    // The inline frame: 40 lamp bits, then level = (raw * 0.25) + 1.
    card.set_sequence(2, 41, 0x80_0000_0001).unwrap();
    card.write(1, -1.0).unwrap(); // raw -8
    assert_eq!(card.compose(1, &mut buf), 8);
    // lamps bit 0 is payload bit 0, lamps bit 39 is payload bit 39 (byte 4, bit 7).
    assert_eq!(buf[..8], [0x01, 0, 0, 0, 0x80, 0xF8, 0xFF, 0]);
    // Motion has a 10 ms cycle (stale after 30 ms); Temps has none.
    card.receive(0x100, false, false, &[0; 8], clock.now());
    card.receive(0x18FE_EE05, true, false, &[0; 4], clock.now());
    assert!(card.read(0).is_ok());
    clock.advance(Duration::from_millis(31));
    assert!(matches!(card.read(0), Err(DeviceError::Stale { .. })));
    assert!(card.read(2).is_ok(), "Temps never goes stale");
    assert_eq!(
        card.health().status,
        Status::Online,
        "one message stale: its channels stale, not the card's devices"
    );
    card.check_stale();
    card.check_stale();
    assert_eq!(card.counters().stale_events, 1, "one episode, counted once");
    card.set_link(false, None);
    assert_eq!(card.health().status, Status::Offline);
    assert!(matches!(card.read(2), Err(DeviceError::Offline)));
}

#[test]
fn each_device_is_as_healthy_as_its_own_messages() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000)));
    let card = card(clock.clone());
    let d = card.devices();
    let statuses = || {
        [
            d.analog_in.as_ref().unwrap().health().status,
            d.digital_in.as_ref().unwrap().health().status,
            d.encoders[0].1.health().status,
            d.analog_out.as_ref().unwrap().health().status,
            d.digital_out.as_ref().unwrap().health().status,
            card.health().status,
        ]
    };
    use Status::{Offline, Online, Stale};
    // Nothing received yet: the inputs stale, the outputs usable.
    assert_eq!(statuses(), [Stale, Stale, Stale, Online, Online, Stale]);
    // Temps (the analog inputs, no cycle) comes; Motion (the digital input and the
    // encoder) does not: only Motion's devices stay stale.
    card.receive(0x18FE_EE05, true, false, &[0; 4], clock.now());
    assert_eq!(statuses(), [Online, Stale, Stale, Online, Online, Online]);
    card.receive(0x100, false, false, &[0; 8], clock.now());
    assert_eq!(statuses(), [Online; 6]);
    let motion_at = d.digital_in.as_ref().unwrap().health().last_good;
    clock.advance(Duration::from_millis(31));
    assert_eq!(statuses(), [Online, Stale, Stale, Online, Online, Online]);
    assert_eq!(
        d.digital_in.as_ref().unwrap().health().last_good,
        motion_at,
        "last good: when its own message last came"
    );
    card.set_link(false, None);
    assert_eq!(statuses(), [Offline; 6]);
}
