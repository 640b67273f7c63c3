//! A remote device as a component sees it, without any network: shape checked against
//! the catalogue, samples taken, stale and offline by age, samples lost counted, writes
//! refused while offline, and a hostile peer's messages refused without a panic.

use device_interface::time::{Clock, MonotonicClock};
use device_interface::{
    AnalogIn, AnalogOut, Device, DeviceError, DigitalOut, Encoder, Interface, RawRange, Scale,
    Status, Unit,
};
use scaleout::config::{Times, ZenohConfig};
use scaleout::remote::{Image, Proxy};
use scaleout::wire::{self, Catalogue, DeviceShape, EncoderShape, Sample, Write};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

fn times() -> Times {
    Times {
        publish: Duration::from_millis(10),
        stale: Duration::from_millis(50),
        offline: Duration::from_millis(2000),
        lease: Duration::from_secs(2),
        request: Duration::from_secs(1),
    }
}

fn scale() -> Scale {
    Scale::linear(
        RawRange { min: 0, max: 4095 },
        -10.0,
        10.0,
        Unit::new("V").unwrap_or_else(|e| panic!("{e}")),
    )
    .unwrap_or_else(|e| panic!("{e}"))
}

fn shape(i: Interface, channels: u32) -> DeviceShape {
    let analog = matches!(i, Interface::AnalogIn | Interface::AnalogOut);
    DeviceShape {
        interface: i,
        name: "sim0".into(),
        channels,
        scales: if analog {
            vec![scale(); channels as usize]
        } else {
            vec![]
        },
        encoder: (i == Interface::Encoder).then_some(EncoderShape {
            resolution: 4096,
            upcounting: true,
        }),
    }
}

fn sample(seq: u64, values: Vec<Option<i64>>) -> Sample {
    Sample {
        seq,
        read_ns: MonotonicClock.now().as_nanos(),
        unix_ns: 0,
        age_ns: Some(1_000_000),
        status: Status::Online,
        error: None,
        values,
    }
}

fn now() -> u64 {
    MonotonicClock.now().as_nanos()
}

#[test]
fn an_input_is_offline_until_its_shape_matched_and_a_sample_came_then_stale_then_offline() {
    let img = Arc::new(Image::new(Interface::AnalogIn, "B", "sim0", 2, times()));
    let ai = Proxy(img.clone());
    assert_eq!(ai.health().status, Status::Offline);
    assert!(matches!(ai.read(0), Err(DeviceError::Offline)));
    // A sample before the shape is known is refused and counted.
    img.take(&sample(1, vec![Some(0), Some(4095)]), now());
    assert_eq!(img.counters.refused.load(Ordering::Relaxed), 1);
    img.adopt(&shape(Interface::AnalogIn, 2));
    img.take(&sample(2, vec![Some(0), Some(4095)]), now());
    assert_eq!(ai.read(0).ok(), Some(-10.0));
    assert_eq!(ai.read(1).ok(), Some(10.0));
    assert_eq!(ai.read_raw(1).ok(), Some(4095));
    assert!(matches!(
        ai.read(2),
        Err(DeviceError::ChannelOutOfRange {
            channel: 2,
            count: 2
        })
    ));
    let h = ai.health();
    assert_eq!(h.status, Status::Online);
    // Its age: the remote age (1 ms) plus the time since it came.
    assert!(
        h.age().is_some_and(|a| a >= Duration::from_millis(1)),
        "{h:?}"
    );
    // Samples 3..=5 never came: counted lost.
    img.take(&sample(6, vec![Some(1), None]), now());
    assert_eq!(img.counters.lost.load(Ordering::Relaxed), 3);
    // A channel the remote could not read is not read here either.
    assert!(ai.read(1).is_err());
    // Stale from 50 ms without a sample, offline from 2 s.
    std::thread::sleep(Duration::from_millis(60));
    assert_eq!(ai.health().status, Status::Stale);
    assert!(matches!(ai.read(0), Err(DeviceError::Stale { .. })));
    let end = std::time::Instant::now() + Duration::from_secs(20);
    while ai.health().status != Status::Offline {
        assert!(std::time::Instant::now() < end, "never offline");
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(matches!(ai.read(0), Err(DeviceError::Offline)));
}

#[test]
fn a_shape_that_does_not_match_keeps_the_device_offline_and_says_why() {
    let img = Arc::new(Image::new(Interface::AnalogIn, "B", "sim0", 4, times()));
    img.adopt(&shape(Interface::AnalogIn, 8));
    img.take(&sample(1, vec![Some(0); 8]), now());
    assert_eq!(Proxy(img.clone()).health().status, Status::Offline);
    let why = img.problem().unwrap_or_default();
    assert!(
        why.contains("8 channels there") && why.contains("declares 4"),
        "{why}"
    );
    // A sample of the wrong length, once the shape matched, is refused and counted; the
    // next good one is taken.
    let img = Arc::new(Image::new(Interface::AnalogIn, "B", "sim0", 2, times()));
    img.adopt(&shape(Interface::AnalogIn, 2));
    img.take(&sample(1, vec![Some(0); 3]), now());
    assert_eq!(img.counters.refused.load(Ordering::Relaxed), 1);
    assert_eq!(Proxy(img.clone()).health().status, Status::Offline);
    img.take(&sample(2, vec![Some(0); 2]), now());
    assert_eq!(Proxy(img).health().status, Status::Online);
}

#[test]
fn a_remote_restart_is_not_counted_as_samples_lost() {
    let img = Arc::new(Image::new(Interface::AnalogIn, "B", "sim0", 1, times()));
    img.adopt(&shape(Interface::AnalogIn, 1));
    img.take(&sample(500, vec![Some(1)]), now());
    assert!(!img.take_refetch());
    img.take(&sample(1, vec![Some(2)]), now());
    img.take(&sample(2, vec![Some(3)]), now());
    assert_eq!(img.counters.lost.load(Ordering::Relaxed), 0);
    // ...but its catalogue is asked for again, once.
    assert!(img.take_refetch());
    assert!(!img.take_refetch());
    // A hostile sequence number is no overflow.
    img.take(&sample(u64::MAX, vec![Some(4)]), now());
    img.take(&sample(u64::MAX, vec![Some(5)]), now());
    assert_eq!(Proxy(img).read_raw(0).ok(), Some(5));
}

#[test]
fn outputs_are_refused_while_offline_and_sent_once_per_write() {
    let img = Arc::new(Image::new(Interface::AnalogOut, "B", "sim0", 2, times()));
    let ao = Proxy(img.clone());
    assert!(matches!(ao.write(0, 1.0), Err(DeviceError::Offline)));
    img.adopt(&shape(Interface::AnalogOut, 2));
    img.take(&sample(1, vec![Some(2048), Some(2048)]), now());
    // Nothing written yet: nothing to send.
    assert_eq!(img.to_send(), None);
    ao.write(1, 10.0).unwrap_or_else(|e| panic!("{e}"));
    // The read-back is the remote gateway's, not what was asked here.
    assert_eq!(ao.read_back_raw(1).ok(), Some(2048));
    assert_eq!(img.to_send(), Some(vec![(1, 4095)]));
    assert_eq!(
        img.to_send(),
        None,
        "sent once per write, never again on its own"
    );
    ao.write(0, -10.0).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        img.to_send(),
        Some(vec![(0, 0)]),
        "only what was written since"
    );
    // Once the gateway stops, writes are refused.
    img.hold();
    assert!(matches!(ao.write(0, 1.0), Err(DeviceError::Held { .. })));
    assert_eq!(img.to_send(), None);
    assert!(matches!(
        ao.write(0, 11.0),
        Err(DeviceError::ValueOutOfRange { .. })
    ));
}

#[test]
fn digital_outputs_and_encoder_commands() {
    let img = Arc::new(Image::new(Interface::DigitalOut, "B", "sim0", 4, times()));
    img.adopt(&shape(Interface::DigitalOut, 4));
    img.take(&sample(1, vec![Some(0); 4]), now());
    let d = Proxy(img.clone());
    d.set_bit(3, true).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        d.check_bit(3).ok(),
        Some(false),
        "until the remote gateway says so"
    );
    assert!(matches!(
        d.set_bit(4, true),
        Err(DeviceError::BitOutOfRange { .. })
    ));
    assert_eq!(img.to_send(), Some(vec![(3, 1)]));
    img.take(&sample(2, vec![Some(0), Some(0), Some(0), Some(1)]), now());
    assert_eq!(d.check_bit(3).ok(), Some(true));

    let img = Arc::new(Image::new(Interface::Encoder, "B", "enc", 2, times()));
    img.adopt(&shape(Interface::Encoder, 2));
    img.take(&sample(1, vec![Some(100), Some(2)]), now());
    let e = Proxy(img.clone());
    assert_eq!((e.position().ok(), e.turn().ok()), (Some(100), Some(2)));
    assert_eq!(Encoder::resolution(&e), 4096);
    e.set_position(7).unwrap_or_else(|err| panic!("{err}"));
    // A position is a command: sent once.
    assert_eq!(img.to_send(), Some(vec![(0, 7)]));
    assert_eq!(img.to_send(), None);
}

#[test]
fn a_hostile_peers_messages_are_refused_without_a_panic() {
    // Garbage, wrong shapes, huge numbers, an oversized payload.
    for bad in [
        &b"not json"[..],
        b"{}",
        b"{\"seq\": -1}",
        b"[1,2,3]",
        b"{\"protocol\":1,\"writer\":\"A\",\"interface\":\"analog_out\",\"device\":\"x\",\"values\":[[4294967296,1]]}",
        b"{\"protocol\":1,\"gateway\":\"B\",\"devices\":[{\"interface\":\"analog_in\",\"name\":\"x\",\"channels\":1,\"scales\":[{\"raw\":{\"min\":5,\"max\":1},\"at_min\":0.0,\"at_max\":1.0,\"formula\":\"ends\",\"unit\":\"V\",\"ties_to_even\":false}]}]}",
    ] {
        assert!(wire::parse::<Sample>(bad).is_err());
        assert!(wire::parse::<Write>(bad).is_err());
        assert!(wire::parse::<Catalogue>(bad).is_err(), "{}", String::from_utf8_lossy(bad));
    }
    let huge = vec![b' '; wire::MAX_PAYLOAD + 1];
    let e = wire::parse::<Sample>(&huge).err().unwrap_or_default();
    assert!(e.contains("more than"), "{e}");
    // A scale crosses the wire exactly.
    let s = scale();
    let back: Scale = wire::parse(&wire::to_bytes(&s)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back, s);
}

#[test]
fn writes_from_another_gateway_reach_only_this_gateways_outputs() {
    let registry = device_interface::Registry::new();
    let img = Arc::new(Image::new(Interface::DigitalOut, "C", "x", 1, times()));
    registry
        .digital_out()
        .register("C/x", "zenoh:C", Arc::new(Proxy(img)))
        .unwrap_or_else(|e| panic!("{e}"));
    let w = |device: &str, interface: Interface, protocol: u32| Write {
        protocol,
        writer: "A".into(),
        interface,
        device: device.into(),
        values: vec![(0, 1)],
    };
    let e = scaleout::local::write("B", &registry, &w("C/x", Interface::DigitalOut, 1))
        .err()
        .unwrap_or_default();
    assert!(e.contains("B has no digital_out device \"C/x\""), "{e}");
    let e = scaleout::local::write("B", &registry, &w("x", Interface::DigitalOut, 2))
        .err()
        .unwrap_or_default();
    assert!(e.contains("protocol 2 from A"), "{e}");
    // A local output: a write naming more channels than it has, or one twice, is refused
    // whole before anything is written.
    let img = Arc::new(Image::new(Interface::DigitalOut, "Z", "y", 2, times()));
    registry
        .digital_out()
        .register("y", "card", Arc::new(Proxy(img.clone())))
        .unwrap_or_else(|e| panic!("{e}"));
    for values in [vec![(0, 1), (0, 0)], vec![(0, 1), (1, 1), (2, 1)]] {
        let mut bad = w("y", Interface::DigitalOut, 1);
        bad.values = values;
        let e = scaleout::local::write("B", &registry, &bad)
            .err()
            .unwrap_or_default();
        assert!(e.contains("names a channel twice or too many"), "{e}");
    }
    assert_eq!(img.to_send(), None, "nothing written");
}

#[test]
fn a_section_is_checked_and_its_times_bounded() {
    let cfg: ZenohConfig =
        toml::from_str("name = \"A\"\nconnect = [\"tcp/127.0.0.1:7447\"]\npublish_ms = 500\n")
            .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(cfg.check(std::path::Path::new(".")), vec![]);
    let t = cfg.times();
    // Stale after five periods (here 2.5 s), but never after offline (1 s).
    assert_eq!(t.stale, t.offline);
    assert_eq!(t.offline, Duration::from_secs(1));
}
