//! The decoder against hostile bytes, the section's checks, and the bus against a board of
//! the test's own (protocol 2.5, with the encoder feature the simulated Uno lacks).
#![allow(clippy::unwrap_used, reason = "test code")]

use crate::board::BoardInfo;
use crate::bus::{FirmataBus, Outcome};
use crate::card::FirmataCard;
use crate::config::FirmataConfig;
use crate::line::Line;
use crate::protocol::{Decoder, encoder_positions, mode, sysex};
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use device_interface::{AnalogIn, DeviceError, DigitalIn, DigitalOut};
use std::io::{Read, Write};
use std::os::fd::{AsFd, BorrowedFd};
use std::os::unix::net::UnixStream;
use std::sync::Arc;
use std::time::Duration;
use testkit::rng::Rng;

fn frames(bytes: &[u8]) -> (Vec<String>, Decoder) {
    let mut d = Decoder::new();
    let mut out = Vec::new();
    for b in bytes {
        if let Some(f) = d.push(*b) {
            out.push(format!("{f:?}"));
        }
    }
    (out, d)
}

#[test]
fn frames_decode_and_errors_are_counted_exactly() {
    let (f, d) = frames(&[
        0xF9, 2, 5, // version
        0x91, 0x20, 0x01, // port 1: pins 13 and 15
        0xE3, 0x7F, 0x07, // A3 = 1023
        0x12, 0x13, // stray: one resync, two framing errors
        0xE0, 0x05, // cut short by the next command byte
        0xA5, 0x01, // unknown command, its data skipped
        0xF0, 0x55, 0x01, 0xF7, // unknown sysex
        0xF0, 0x71, 0x41, 0x00, 0xF7, // STRING_DATA "A"
    ]);
    assert_eq!(
        f,
        [
            "Version { major: 2, minor: 5 }",
            "Digital { port: 1, value: 160 }",
            "Analog { channel: 3, value: 1023 }",
            "Sysex { command: 113, data: [65, 0] }",
        ]
    );
    let c = d.counts();
    assert_eq!(
        (c.messages, c.framing_errors, c.unknown_commands, c.resyncs),
        (4, 4, 2, 3),
        "{c:?}"
    );
    assert_eq!(c.bytes, 24);
}

#[test]
fn random_garbage_never_panics_nor_sticks_the_decoder() {
    let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15);
    let mut d = Decoder::new();
    for round in 0..20_000 {
        let len = (rng.next_u64() % 300) as usize;
        for _ in 0..len {
            let r = rng.next_u64();
            // Mostly command-ish and data bytes, sometimes a sysex start or end.
            let b = match r % 8 {
                0 => 0xF0,
                1 => 0xF7,
                2..=4 => (r >> 8) as u8 | 0x80,
                _ => (r >> 8) as u8 & 0x7F,
            };
            let _ = d.push(b);
        }
        if round % 97 == 0 {
            for _ in 0..5000 {
                let _ = d.push(0x41);
            }
        }
        // Whatever came before, a whole message after it is decoded.
        let mut got = None;
        for b in [0xF9, 2, 5] {
            got = d.push(b).map(|f| format!("{f:?}"));
        }
        assert_eq!(
            got.as_deref(),
            Some("Version { major: 2, minor: 5 }"),
            "round {round}"
        );
    }
    let c = d.counts();
    assert!(
        c.framing_errors > 0 && c.resyncs > 0 && c.unknown_commands > 0,
        "{c:?}"
    );
}

#[test]
fn encoder_positions_are_sign_and_magnitude() {
    let data = [
        0x00, 0x7F, 0x01, 0x00, 0x00, 0x41, 0x05, 0x00, 0x00, 0x00, 0x02,
    ];
    let (p, whole) = encoder_positions(&data);
    assert_eq!(p.collect::<Vec<_>>(), [(0, 255), (1, -5)]);
    assert!(!whole);
}

fn section(s: &str) -> FirmataConfig {
    toml::from_str(&format!("port = \"/dev/ttyACM0\"\n{s}")).unwrap()
}

#[test]
fn the_section_alone_is_bounded() {
    for (s, key, msg) in [
        (
            "digital_in = [{ pin = 2 }]\ndigital_out = [{ pin = 2 }]",
            "digital_out[0].pin",
            "pin 2 is digital_in[0].pin already",
        ),
        (
            "digital_out = [{ pin = 128 }]",
            "digital_out[0].pin",
            "Firmata numbers pins 0-127",
        ),
        (
            "analog_in = [{ channel = 16 }]",
            "analog_in[0].channel",
            "A0-A15",
        ),
        (
            "pwm = [{ pin = 3, initial = 1.5 }]",
            "pwm[0].initial",
            "a duty cycle 0-1",
        ),
        (
            "servo = [{ pin = 9, min_us = 2000, max_us = 1000 }]",
            "servo[0].max_us",
            "min_us below max_us",
        ),
        (
            "encoder = [{ a = 2, b = 2, resolution = 100 }]",
            "encoder[0].b",
            "pin 2 is encoder[0].a already",
        ),
        ("baud = 0", "baud", "300-4000000"),
        ("sampling_ms = 0", "sampling_ms", "1-16383"),
        ("reference_volts = nan", "reference_volts", "above 0"),
    ] {
        let e = section(s).check().unwrap_err();
        assert_eq!(e.key.as_deref(), Some(key), "{s}: {e:?}");
        assert!(e.message.contains(msg), "{s}: {e:?}");
    }
    let mut c = section("");
    c.port = String::new();
    assert_eq!(c.check().unwrap_err().key.as_deref(), Some("port"));
}

/// A board of 20 pins, protocol 2.5: pins 2 and 3 encoder-capable, 4 with a pull-up,
/// 14–19 analog A0–A5.
fn board_replies() -> (Vec<u8>, Vec<u8>) {
    let mut caps = Vec::new();
    for pin in 0..20u8 {
        if pin >= 2 {
            caps.extend_from_slice(&[mode::INPUT, 1, mode::OUTPUT, 1, mode::PULLUP, 1]);
        }
        if pin == 2 || pin == 3 {
            caps.extend_from_slice(&[mode::ENCODER, 1]);
        }
        if pin >= 14 {
            caps.extend_from_slice(&[mode::ANALOG, 10]);
        }
        caps.push(0x7F);
    }
    let map: Vec<u8> = (0..20u8)
        .map(|p| if p >= 14 { p - 14 } else { 0x7F })
        .collect();
    (caps, map)
}

#[test]
fn the_board_is_checked_and_its_gaps_named() {
    let (caps, map) = board_replies();
    let mut b = BoardInfo {
        protocol: (2, 5),
        ..BoardInfo::default()
    };
    b.set_capabilities(&caps).unwrap();
    b.set_mapping(&map).unwrap();
    let e = section("pwm = [{ pin = 3 }]").check_board(&b).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("pwm[0].pin"));
    assert!(
        e.message
            .starts_with("pin 3 cannot be pwm: its modes are input, output, input_pullup, encoder"),
        "{e:?}"
    );
    assert!(e.message.ends_with("pwm pins: none)"), "{e:?}");
    assert!(
        section("encoder = [{ a = 2, b = 3, resolution = 400 }]")
            .check_board(&b)
            .is_ok()
    );
    assert!(b.set_capabilities(&[0x00]).is_err());
    assert!(b.set_capabilities(&[0x00, 0x01]).is_err());
}

/// The host's end of a socket pair as a serial line.
struct Sock(UnixStream);
impl Line for Sock {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.0.read(buf)
    }
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.0.write(data)
    }
    fn fd(&self) -> BorrowedFd<'_> {
        self.0.as_fd()
    }
}

/// Steps `bus` until `done`, the board answering what it is sent by `answer`.
fn drive(
    bus: &mut FirmataBus,
    board: &mut UnixStream,
    sent: &mut Vec<u8>,
    mut done: impl FnMut(&FirmataBus, &[u8]) -> bool,
) {
    let end = std::time::Instant::now() + Duration::from_secs(10);
    let (caps, map) = board_replies();
    while !done(bus, sent) {
        assert!(std::time::Instant::now() < end, "sent so far: {sent:x?}");
        let _ = bus.step(MonotonicClock.now());
        let mut buf = [0u8; 4096];
        if let Ok(n) = board.read(&mut buf) {
            let from = sent.len();
            sent.extend_from_slice(&buf[..n]);
            let new = &sent[from..];
            if new.contains(&0xF9) {
                board.write_all(&[0xF9, 2, 5]).unwrap();
            }
            if new.windows(2).any(|w| w == [0xF0, sysex::CAPABILITY_QUERY]) {
                board
                    .write_all(&[0xF0, sysex::CAPABILITY_RESPONSE])
                    .unwrap();
                board.write_all(&caps).unwrap();
                board.write_all(&[0xF7]).unwrap();
            }
            if new
                .windows(2)
                .any(|w| w == [0xF0, sysex::ANALOG_MAPPING_QUERY])
            {
                board
                    .write_all(&[0xF0, sysex::ANALOG_MAPPING_RESPONSE])
                    .unwrap();
                board.write_all(&map).unwrap();
                board.write_all(&[0xF7]).unwrap();
            }
            if new.windows(2).any(|w| w == [0xD0, 1]) {
                // REPORT_DIGITAL on port 0: its levels at once, pin 4 high.
                board.write_all(&[0x90, 0x10, 0x00]).unwrap();
            }
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// The card, its bus side, the board's end of the line and how many opens were tried.
type Fake = (
    Arc<FirmataCard>,
    FirmataBus,
    UnixStream,
    Arc<std::sync::atomic::AtomicU32>,
);

/// A card of `section` and its bus side over a socket pair, opened once (then "unplugged").
fn fake(section_text: &str) -> Fake {
    fake_at(section_text, "/dev/ttyACM0")
}

/// [`fake`] with `port` as the section's port.
fn fake_at(section_text: &str, port: &str) -> Fake {
    let mut config = section(section_text);
    config.port = port.to_string();
    config.check().unwrap();
    let card = Arc::new(FirmataCard::new(&config, Arc::new(MonotonicClock)).unwrap());
    let (host, board) = UnixStream::pair().unwrap();
    host.set_nonblocking(true).unwrap();
    board.set_nonblocking(true).unwrap();
    let mut host = Some(host);
    let opens = Arc::new(std::sync::atomic::AtomicU32::new(0));
    let counted = opens.clone();
    let bus = FirmataBus::with_opener(
        card.clone(),
        Box::new(move |_, _| {
            counted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            host.take()
                .map(|h| Box::new(Sock(h)) as Box<dyn Line>)
                .ok_or_else(|| std::io::Error::other("unplugged"))
        }),
    );
    (card, bus, board, opens)
}

#[test]
fn a_protocol_2_5_board_with_encoders_is_set_up_and_read() {
    let (card, mut bus, mut board, _) = fake(
        "banner_ms = 100\ndigital_in = [{ pin = 4, pullup = true }]\ndigital_out = [{ pin = 9, initial = true }]\nencoder = [{ a = 2, b = 3, resolution = 400 }]",
    );
    let mut sent = Vec::new();
    drive(&mut bus, &mut board, &mut sent, |_, _| card.is_online());
    // Nothing was sent before the banner wait ended with a version query.
    assert_eq!(sent[0], 0xF9);
    let has = |s: &[u8], w: &[u8]| s.windows(w.len()).any(|x| x == w);
    assert!(
        has(&sent, &[0xF4, 4, mode::PULLUP]),
        "INPUT_PULLUP from 2.5: {sent:x?}"
    );
    assert!(
        has(&sent, &[0xF0, 0x61, 0x00, 0, 2, 3, 0xF7]),
        "encoder attached: {sent:x?}"
    );
    assert!(
        has(&sent, &[0xF5, 9, 1]),
        "pin 9 high, pin by pin from 2.5: {sent:x?}"
    );
    assert!(!has(&sent, &[0x91]), "no port-wide write on 2.5: {sent:x?}");
    assert!(card.read_bit(0).unwrap(), "pin 4 high");
    // Encoder reports: +300, then −50 (sign bit), counted through.
    let enc = card.devices().encoders.remove(0).1;
    board
        .write_all(&[0xF0, 0x61, 0x00, 0x2C, 0x02, 0, 0, 0xF7])
        .unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, _| {
        enc.position().ok() == Some(0)
    });
    board
        .write_all(&[
            0xF0, 0x61, 0x00, 0x2C, 0x02, 0, 0, 0xF7, 0xF0, 0x61, 0x40, 50, 0, 0, 0, 0xF7,
        ])
        .unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, _| {
        enc.position().ok() == Some(50) && enc.turn().ok() == Some(-1)
    });
    // An output write is one SET_DIGITAL_PIN_VALUE (2.5: the port's other pins untouched).
    let from = sent.len();
    card.set_bit(0, false).unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, s| {
        has(&s[from..], &[0xF5, 9, 0])
    });
    // Settling: the board is asked for pin 9's state and says high, not low as written.
    let from = sent.len();
    std::thread::scope(|s| {
        let settle = s.spawn(|| card.settle(std::time::Instant::now() + Duration::from_secs(5)));
        drive(&mut bus, &mut board, &mut sent, |_, s| {
            has(&s[from..], &[0xF0, sysex::PIN_STATE_QUERY, 9, 0xF7])
        });
        board
            .write_all(&[0xF0, sysex::PIN_STATE_RESPONSE, 9, mode::OUTPUT, 1, 0xF7])
            .unwrap();
        drive(&mut bus, &mut board, &mut sent, |_, _| settle.is_finished());
        let e = settle.join().unwrap().unwrap_err().to_string();
        assert!(
            e.ends_with("pin 9 is 1 on the board, not 0 as written"),
            "{e}"
        );
    });
    assert!(card.set_bit(0, true).is_err(), "no writes after settle");
    // The board gone: offline, and no reopen succeeds.
    drop(board);
    let t0 = MonotonicClock.now();
    let mut outcome = Outcome::Pending;
    while card.is_online() && MonotonicClock.now().as_nanos() < t0.as_nanos() + 5_000_000_000 {
        outcome = bus.step(MonotonicClock.now()).0;
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(!card.is_online(), "{outcome:?}");
    assert!(
        card.counters().last_error.unwrap().contains("hung up"),
        "{:?}",
        card.counters()
    );
}

/// An input whose port the board has not reported is stale, not its level of before; an
/// analog report beyond 10 bits is dropped and counted; a flood is taken 16 KiB a step;
/// the stop turns the board's reports off.
#[test]
fn unreported_inputs_are_stale_and_bad_reports_dropped() {
    let (card, mut bus, mut board, _) = fake(
        "banner_ms = 100\ndigital_in = [{ pin = 4 }, { pin = 10 }]\nanalog_in = [{ channel = 0 }]",
    );
    let mut sent = Vec::new();
    drive(&mut bus, &mut board, &mut sent, |_, _| card.is_online());
    // Port 0 was reported at once; port 1 (pin 10) never was: online after the wait.
    assert!(card.read_bit(0).unwrap());
    assert!(
        matches!(card.read_bit(1), Err(DeviceError::Stale { .. })),
        "{:?}",
        card.read_bit(1)
    );
    board.write_all(&[0x91, 0x04, 0x00]).unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, _| {
        card.read_bit(1).is_ok()
    });
    assert!(card.read_bit(1).unwrap(), "pin 10 high");
    // 16383 on a 10-bit channel: dropped and counted; 1023 taken.
    board.write_all(&[0xE0, 0x7F, 0x7F]).unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, _| {
        card.counters().bad_values == 1
    });
    assert!(matches!(card.read_raw(0), Err(DeviceError::Stale { .. })));
    board.write_all(&[0xE0, 0x7F, 0x07]).unwrap();
    drive(&mut bus, &mut board, &mut sent, |_, _| {
        card.read_raw(0).ok() == Some(1023)
    });
    // 40 KiB at once: one step takes 16 KiB and asks to be called again at once.
    let before = card.counters().line.bytes;
    board.write_all(&[0x12; 40 * 1024]).unwrap();
    let now = MonotonicClock.now();
    let (_, next) = bus.step(now);
    let took = card.counters().line.bytes - before;
    assert_eq!(took, crate::bus::MAX_RX_PER_STEP as u64);
    assert!(next <= MonotonicClock.now(), "called again at once");
    // Stopping: the reports are turned off before the port closes.
    let from = sent.len();
    bus.release();
    let mut rest = Vec::new();
    let _ = board.read_to_end(&mut rest);
    sent.extend_from_slice(&rest);
    let off = &sent[from..];
    let has = |w: &[u8]| off.windows(w.len()).any(|x| x == w);
    assert!(
        has(&[0xC0, 0]) && has(&[0xD0, 0]) && has(&[0xD1, 0]),
        "{off:x?}"
    );
}

/// A board that lacks what the section asks for is not opened again (each open resets an
/// Uno) until its port leads to another device.
#[test]
fn a_refused_board_is_not_reopened_until_its_port_changes() {
    let dir = std::env::temp_dir().join(format!("hwgw-refused-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let port = dir.join("uno");
    std::fs::write(&port, "").unwrap();
    let (card, mut bus, mut board, opens) = fake_at(
        "banner_ms = 100\npwm = [{ pin = 3 }]",
        port.to_str().unwrap(),
    );
    let mut sent = Vec::new();
    drive(&mut bus, &mut board, &mut sent, |b, _| {
        card.counters().link == "refused" && b.fd().is_none()
    });
    let opened = opens.load(std::sync::atomic::Ordering::Relaxed);
    let t = MonotonicClock.now();
    for s in 1..=5u64 {
        let (outcome, _) = bus.step(Timestamp::from_nanos(t.as_nanos() + s * 10_000_000_000));
        assert!(matches!(outcome, Outcome::Refused(_)), "{outcome:?}");
    }
    assert_eq!(
        opens.load(std::sync::atomic::Ordering::Relaxed),
        opened,
        "not opened again while the port is the same device"
    );
    // The port made anew (a board plugged back): opened again.
    let same = crate::line::identity(port.to_str().unwrap());
    while crate::line::identity(port.to_str().unwrap()) == same {
        // Until the file system's clock has moved on (its change time tells them apart).
        std::fs::remove_file(&port).unwrap();
        std::thread::sleep(Duration::from_millis(2));
        std::fs::write(&port, "").unwrap();
    }
    let _ = bus.step(Timestamp::from_nanos(t.as_nanos() + 100_000_000_000));
    assert_eq!(opens.load(std::sync::atomic::Ordering::Relaxed), opened + 1);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn only_serial_ports_are_opened() {
    for (path, why) in [
        (
            "/dev/null",
            "/dev/null is not a serial port: no tty driver owns device 1:3",
        ),
        (
            "/dev/tty",
            "/dev/tty is not a serial port: device 5:0 is the tty driver /dev/tty's (system:/dev/tty)",
        ),
        (
            "/proc/tty/drivers",
            "/proc/tty/drivers is not a serial port: not a character device",
        ),
    ] {
        let e = crate::line::check_serial(path).unwrap_err().to_string();
        assert!(e.starts_with(why), "{e}");
    }
    assert!(crate::line::check_serial("/nonexistent/ttyACM0").is_err());
    // A pty's slave end is one.
    let (_master, slave) = mio_serial::SerialStream::pair().unwrap();
    let path = mio_serial::SerialPort::name(&slave).unwrap();
    crate::line::check_serial(&path).unwrap();
    crate::line::check_port(&path).unwrap();
}

/// What `hwgw check` refuses of a port from its device number alone (nothing is opened:
/// that would reset an Uno); a port not there yet is a board not plugged in yet.
#[test]
fn ports_that_can_never_be_serial_lines_are_refused_before_opening() {
    for (path, why) in [
        (
            "/dev/null",
            "/dev/null is not a serial port: it is a memory device (1:3",
        ),
        (
            "/dev/zero",
            "/dev/zero is not a serial port: it is a memory device (1:5",
        ),
        (
            "/dev/tty",
            "/dev/tty is not a serial port: it is /dev/tty, the controlling terminal (5:0)",
        ),
        (
            "/etc/passwd",
            "/etc/passwd is not a serial port: it is a regular file, not a character device",
        ),
        (
            "/dev",
            "/dev is not a serial port: it is a directory, not a character device",
        ),
    ] {
        let e = crate::line::check_port(path).unwrap_err().to_string();
        assert!(e.starts_with(why), "{e}");
    }
    // Virtual consoles and the console by their numbers: see driver_api::node's tests
    // (a machine may lack the nodes).
    crate::line::check_port("/nonexistent/ttyACM0").unwrap();
}
