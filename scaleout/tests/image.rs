//! A remote device as a component sees it, without any network: shape checked against
//! the catalogue, samples taken, stale and offline by age, samples lost counted, writes
//! refused while offline, and a hostile peer's messages refused without a panic.

use device_interface::time::{Clock, MonotonicClock};
use device_interface::{
    AnalogIn, AnalogOut, Device, DeviceError, DigitalOut, Encoder, Interface, RawRange, Scale,
    Status, Unit,
};
use scaleout::config::{Times, ZenohConfig};
use scaleout::outbox::Outbox;
use scaleout::remote::{Image, Proxy};
use scaleout::wire::{self, Catalogue, DeviceShape, EncoderShape, Sample, Write};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

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

/// An outbox failing writes after the test times' request timeout (1 s), retrying every
/// 100 ms.
fn outbox() -> Outbox {
    Outbox::new("A", 7, times().request, Duration::from_millis(100))
}

/// What a write message carries: `(channel, raw)` values, its sequence number, and
/// whether it is a repeat.
type Sent = (Vec<(u32, i64)>, u64, bool);

/// What `o` sends for `img` at `at`.
fn sent(o: &mut Outbox, img: &Image, at: Instant) -> Option<Sent> {
    o.next(img, at)
        .map(|out| (out.write.values, out.write.seq, out.retry))
}

#[test]
fn outputs_are_refused_while_offline_and_sent_until_acknowledged() {
    let img = Arc::new(Image::new(Interface::AnalogOut, "B", "sim0", 2, times()));
    let ao = Proxy(img.clone());
    let mut o = outbox();
    let t0 = Instant::now();
    assert!(matches!(ao.write(0, 1.0), Err(DeviceError::Offline)));
    img.adopt(&shape(Interface::AnalogOut, 2));
    img.take(&sample(1, vec![Some(2048), Some(2048)]), now());
    // Nothing written yet: nothing to send.
    assert_eq!(sent(&mut o, &img, t0), None);
    ao.write(1, 10.0).unwrap_or_else(|e| panic!("{e}"));
    // The read-back is the remote gateway's, not what was asked here.
    assert_eq!(ao.read_back_raw(1).ok(), Some(2048));
    let first = o.next(&img, t0).unwrap_or_else(|| panic!("nothing sent"));
    assert_eq!(
        (first.write.values.clone(), first.write.seq),
        (vec![(1, 4095)], 1)
    );
    assert_eq!((first.write.writer.as_str(), first.write.session), ("A", 7));
    let n = first.numbers[0].1;
    assert!(
        AnalogOut::delivery(&ao, 1)
            .and_then(|d| d.outcome(n))
            .is_none(),
        "pending"
    );
    // Not again before the retry interval; then the same message, same number.
    assert_eq!(sent(&mut o, &img, t0 + Duration::from_millis(50)), None);
    assert_eq!(
        sent(&mut o, &img, t0 + Duration::from_millis(100)),
        Some((vec![(1, 4095)], 1, true))
    );
    // A newer value of another output: a new message with every unacknowledged output.
    ao.write(0, -10.0).unwrap_or_else(|e| panic!("{e}"));
    let second = o
        .next(&img, t0 + Duration::from_millis(120))
        .unwrap_or_else(|| panic!("nothing sent"));
    assert_eq!(
        (second.write.values.clone(), second.write.seq, second.retry),
        (vec![(0, 0), (1, 4095)], 2, false)
    );
    // The acknowledgement settles both; nothing more goes out.
    img.answered(&second.numbers, &[]);
    assert!(matches!(
        AnalogOut::delivery(&ao, 1).and_then(|d| d.outcome(n)),
        Some(Ok(()))
    ));
    assert_eq!(sent(&mut o, &img, t0 + Duration::from_millis(400)), None);
    assert_eq!(img.counters.writes_acked.load(Ordering::Relaxed), 1);
    // Once the gateway stops, writes are refused.
    img.hold();
    assert!(matches!(ao.write(0, 1.0), Err(DeviceError::Held { .. })));
    assert_eq!(sent(&mut o, &img, t0 + Duration::from_millis(500)), None);
    assert!(matches!(
        ao.write(0, 11.0),
        Err(DeviceError::ValueOutOfRange { .. })
    ));
}

#[test]
fn a_write_never_acknowledged_fails_after_the_request_timeout_and_is_counted() {
    let img = Arc::new(Image::new(Interface::AnalogOut, "B", "sim0", 1, times()));
    img.adopt(&shape(Interface::AnalogOut, 1));
    img.take(&sample(1, vec![Some(0)]), now());
    let ao = Proxy(img.clone());
    let mut o = outbox();
    let t0 = Instant::now();
    ao.write(0, 1.0).unwrap_or_else(|e| panic!("{e}"));
    let n = AnalogOut::delivery(&ao, 0).map_or(0, |d| d.taken);
    assert!(o.next(&img, t0).is_some());
    // Sent again, every retry interval, until the timeout (1 s) passes; then failed.
    let repeats = (1..10)
        .filter(|k| o.next(&img, t0 + Duration::from_millis(100 * k)).is_some())
        .count();
    assert_eq!(repeats, 9);
    assert!(o.next(&img, t0 + Duration::from_millis(1000)).is_none());
    let d = AnalogOut::delivery(&ao, 0).unwrap_or_default();
    assert!(
        matches!(d.outcome(n), Some(Err(DeviceError::Undelivered { .. }))),
        "{d:?}"
    );
    assert_eq!(img.counters.writes_failed.load(Ordering::Relaxed), 1);
    assert!(
        img.problem()
            .unwrap_or_default()
            .contains("write to B failed")
    );
    // A late acknowledgement of the failed write changes nothing; the next write is
    // pending again, and a refusal fails it at once.
    let m = {
        ao.write(0, 2.0).unwrap_or_else(|e| panic!("{e}"));
        AnalogOut::delivery(&ao, 0).map_or(0, |d| d.taken)
    };
    let out = o
        .next(&img, t0 + Duration::from_millis(1100))
        .unwrap_or_else(|| panic!("nothing sent"));
    img.answered(&out.numbers, &[(0, "held".to_string())]);
    assert!(matches!(
        AnalogOut::delivery(&ao, 0).and_then(|d| d.outcome(m)),
        Some(Err(DeviceError::Undelivered { .. }))
    ));
    assert_eq!(img.counters.writes_refused.load(Ordering::Relaxed), 1);
    // Stopping fails what is still on its way.
    ao.write(0, 3.0).unwrap_or_else(|e| panic!("{e}"));
    img.hold();
    assert_eq!(img.counters.writes_failed.load(Ordering::Relaxed), 2);
}

#[test]
fn a_steady_writer_whose_writes_are_acknowledged_never_times_out() {
    // A component writing every 10 ms for 3 s (three request timeouts), each message
    // acknowledged as soon as it is sent: nothing fails, and the last value is delivered.
    let img = Arc::new(Image::new(Interface::AnalogOut, "B", "sim0", 1, times()));
    img.adopt(&shape(Interface::AnalogOut, 1));
    img.take(&sample(1, vec![Some(0)]), now());
    let ao = Proxy(img.clone());
    let mut o = outbox();
    let t0 = Instant::now();
    for k in 0..300u32 {
        ao.write(0, f64::from(k % 20) * 0.5 - 5.0)
            .unwrap_or_else(|e| panic!("{e}"));
        if let Some(out) = o.next(&img, t0 + Duration::from_millis(10 * u64::from(k))) {
            img.answered(&out.numbers, &[]);
        }
    }
    assert_eq!(img.counters.writes_failed.load(Ordering::Relaxed), 0);
    let last = AnalogOut::delivery(&ao, 0).unwrap_or_default();
    assert!(matches!(last.outcome(last.taken), Some(Ok(()))), "{last:?}");
    // Once the gateway stops, nothing more goes out, and a write racing the stop fails.
    img.hold();
    assert!(o.next(&img, t0 + Duration::from_secs(4)).is_none());
    assert!(matches!(ao.write(0, 1.0), Err(DeviceError::Held { .. })));
}

#[test]
fn a_hostile_write_refused_whole_is_answered_small_and_not_remembered() {
    let registry = device_interface::Registry::new();
    let mut writes = scaleout::local::Writes::default();
    // A 1 MB device name nobody has, and 500 000 values.
    let w = Write {
        protocol: 1,
        writer: "x".repeat(1 << 20),
        interface: Interface::AnalogOut,
        device: "d".repeat(1 << 20),
        values: vec![(0, 0); 500_000],
        seq: 1,
        session: 1,
    };
    let (r, repeated) = writes.apply("B", &registry, &w);
    assert!(!repeated);
    assert!(r.refused.len() <= 4096, "{} refusals", r.refused.len());
    let bytes = wire::to_bytes(&r).len();
    assert!(bytes < 1 << 20, "a reply of {bytes} bytes");
    // Not remembered: the same message again is carried out (and refused) again.
    assert!(!writes.apply("B", &registry, &w).1);
}

#[test]
fn digital_outputs_and_encoder_commands() {
    let img = Arc::new(Image::new(Interface::DigitalOut, "B", "sim0", 4, times()));
    img.adopt(&shape(Interface::DigitalOut, 4));
    img.take(&sample(1, vec![Some(0); 4]), now());
    let d = Proxy(img.clone());
    let mut o = outbox();
    let t0 = Instant::now();
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
    assert_eq!(sent(&mut o, &img, t0), Some((vec![(3, 1)], 1, false)));
    img.take(&sample(2, vec![Some(0), Some(0), Some(0), Some(1)]), now());
    assert_eq!(d.check_bit(3).ok(), Some(true));

    let img = Arc::new(Image::new(Interface::Encoder, "B", "enc", 2, times()));
    img.adopt(&shape(Interface::Encoder, 2));
    img.take(&sample(1, vec![Some(100), Some(2)]), now());
    let e = Proxy(img.clone());
    let mut o = outbox();
    assert_eq!((e.position().ok(), e.turn().ok()), (Some(100), Some(2)));
    assert_eq!(Encoder::resolution(&e), 4096);
    e.set_position(7).unwrap_or_else(|err| panic!("{err}"));
    // A position is a command: sent until acknowledged, then never again.
    let out = o.next(&img, t0).unwrap_or_else(|| panic!("nothing sent"));
    assert_eq!(out.write.values, vec![(0, 7)]);
    img.answered(&out.numbers, &[]);
    assert_eq!(sent(&mut o, &img, t0 + Duration::from_secs(5)), None);
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
    let e = wire::parse::<Sample>(&huge)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
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
        seq: 1,
        session: 1,
    };
    let e = scaleout::local::write("B", &registry, &w("C/x", Interface::DigitalOut, 1))
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(e.contains("B has no digital_out device \"C/x\""), "{e}");
    let e = scaleout::local::write("B", &registry, &w("x", Interface::DigitalOut, 2))
        .err()
        .map(|e| e.to_string())
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
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("names a channel twice or too many"), "{e}");
    }
    assert!(img.pending().is_empty(), "nothing written");
}

#[test]
fn a_message_sent_again_is_acknowledged_not_written_again() {
    let registry = device_interface::Registry::new();
    let sim = Arc::new(CountingOut::default());
    registry
        .digital_out()
        .register("y", "card", sim.clone())
        .unwrap_or_else(|e| panic!("{e}"));
    let mut writes = scaleout::local::Writes::default();
    let w = |seq: u64, session: u64, on: i64| Write {
        protocol: 1,
        writer: "A".into(),
        interface: Interface::DigitalOut,
        device: "y".into(),
        values: vec![(0, on)],
        seq,
        session,
    };
    assert!(!writes.apply("B", &registry, &w(1, 5, 1)).1);
    assert_eq!(sim.writes(), 1);
    // The same message again: acknowledged, not written (B's watchdog sees no refresh).
    let (r, repeated) = writes.apply("B", &registry, &w(1, 5, 1));
    assert!(repeated && r.refused.is_empty());
    assert_eq!(sim.writes(), 1);
    // An older one arriving late is superseded.
    assert!(!writes.apply("B", &registry, &w(2, 5, 0)).1);
    assert!(writes.apply("B", &registry, &w(1, 5, 1)).1);
    assert_eq!(sim.writes(), 2);
    assert!(
        !sim.on(),
        "the late older value did not overwrite the newer"
    );
    // A restarted writer (another run) counts from 1 again and is written.
    assert!(!writes.apply("B", &registry, &w(1, 6, 1)).1);
    assert_eq!(sim.writes(), 3);
    // A write refused whole answers every value refused, with why.
    let mut bad = w(3, 5, 1);
    bad.device = "nosuch".into();
    let (r, _) = writes.apply("B", &registry, &bad);
    assert_eq!(r.refused.len(), 1);
    assert!(
        r.refused[0].1.contains("has no digital_out device"),
        "{:?}",
        r.refused
    );
}

/// A one-bit output that counts its writes.
#[derive(Default)]
struct CountingOut {
    n: std::sync::atomic::AtomicU64,
    on: std::sync::atomic::AtomicBool,
}

impl CountingOut {
    fn writes(&self) -> u64 {
        self.n.load(Ordering::Relaxed)
    }
    fn on(&self) -> bool {
        self.on.load(Ordering::Relaxed)
    }
}

impl Device for CountingOut {
    fn health(&self) -> device_interface::Health {
        let now = MonotonicClock.now();
        device_interface::Health::online_if(true, now.as_nanos(), now)
    }
}

impl DigitalOut for CountingOut {
    fn output_count(&self) -> u32 {
        1
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        if bit != 0 {
            return Err(DeviceError::BitOutOfRange { bit, count: 1 });
        }
        self.n.fetch_add(1, Ordering::Relaxed);
        self.on.store(value, Ordering::Relaxed);
        Ok(())
    }
    fn check_bit(&self, _bit: u32) -> Result<bool, DeviceError> {
        Ok(self.on())
    }
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
