//! The Firmata card against the genuine StandardFirmata firmware on a simulated Uno
//! (simavr, through the project's harness): the pins the firmware drives are read in the
//! simulator, the pins the test drives are read through the card. One simulation at a time
//! (each takes a whole core).
#![allow(clippy::unwrap_used, reason = "test code")]

use device_interface::conformance;
use device_interface::time::MonotonicClock;
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut};
use driver_serial::bus::FirmataBus;
use driver_serial::card::FirmataCard;
use driver_serial::component::FirmataIo;
use driver_serial::config::FirmataConfig;
use rtt::{Runtime, RuntimeOptions};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use testkit::uno::millivolts_for;
use testkit::{SimUno, TempDir, wait_until};

/// One simulation at a time.
static ONE: Mutex<()> = Mutex::new(());

fn one() -> MutexGuard<'static, ()> {
    ONE.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A card of `section` (its port replaced by `port`), its bus side started.
struct Up {
    card: Arc<FirmataCard>,
    task: rtt::TaskContext,
    _rt: Runtime,
}

fn up(port: &str, section: &str) -> Result<Up, String> {
    let mut config: FirmataConfig = toml::from_str(&format!("port = \"\"\n{section}")).unwrap();
    config.port = port.into();
    config.check().map_err(|e| e.to_string())?;
    let card = FirmataCard::new(&config, Arc::new(MonotonicClock)).map_err(|e| e.to_string())?;
    let card = Arc::new(card);
    let rt = Runtime::new(
        Arc::new(device_interface::Registry::new()),
        RuntimeOptions::default(),
    )
    .unwrap();
    let task = FirmataIo::add(
        &rt,
        "uno",
        FirmataBus::new(card.clone()),
        Default::default(),
    )
    .unwrap();
    task.start().map_err(|e| e.to_string())?;
    Ok(Up {
        card,
        task,
        _rt: rt,
    })
}

const PINS: &str = r#"
digital_in = [{ pin = 2 }, { pin = 3 }, { pin = 4, pullup = true }, { pin = 7 }]
digital_out = [{ pin = 8 }, { pin = 10 }, { pin = 12 }, { pin = 13, initial = true }]
analog_in = [{ channel = 0 }, { channel = 1 }, { channel = 5 }]
pwm = [{ pin = 5, initial = 0.5 }, { pin = 6 }]
servo = [{ pin = 9, min_us = 600, max_us = 2400 }]
"#;

#[test]
fn inputs_outputs_and_pwm_on_standard_firmata() {
    let _one = one();
    let mut sim = SimUno::start().unwrap();
    let u = up(sim.pty().to_str().unwrap(), PINS).unwrap();
    let card = u.card.clone();
    wait_until("the board online", || card.is_online());
    let c = card.counters();
    assert_eq!(
        c.board.as_deref(),
        Some("StandardFirmata.ino 2.4 (protocol 2.4), 20 pins"),
        "{c:?}"
    );
    // The initial outputs were sent at set-up; pin 4's pull-up is on (protocol 2.4: a 1
    // written to the input through its port, which has no digital output), pin 2's is not.
    assert!(sim.pin(13).unwrap().level);
    assert!(sim.pullup(4).unwrap(), "pin 4's pull-up");
    assert!(!sim.pullup(2).unwrap(), "pin 2 has none");
    let pwm = sim.pin(5).unwrap();
    assert!((pwm.duty - 0.5).abs() < 0.01, "{pwm:?}");
    // Digital inputs, each alone.
    for (bit, pin) in [2u8, 3, 4, 7].into_iter().enumerate() {
        for level in [true, false, true] {
            sim.input(pin, level).unwrap();
            wait_until("the input's level", || {
                card.read_bit(bit as u32).ok() == Some(level)
            });
        }
    }
    // Analog inputs in volts: 10 bits over AVCC (5 V).
    for (ch, mv) in [(0u8, 2500u32), (1, 1234), (5, 5000)] {
        sim.adc(ch, mv).unwrap();
        let i = [0, 1, 5].iter().position(|c| *c == ch).unwrap() as u32;
        let raw = i64::from(mv * 1023 / 5000);
        wait_until("the analog report", || card.read_raw(i).ok() == Some(raw));
        let v = AnalogIn::read(card.as_ref(), i).unwrap();
        assert!((v - raw as f64 / 1023.0 * 5.0).abs() < 1e-12, "{v}");
    }
    // Digital outputs.
    for (bit, pin) in [8u8, 10, 12, 13].into_iter().enumerate() {
        for level in [true, false] {
            card.set_bit(bit as u32, level).unwrap();
            wait_until("the pin's level", || sim.pin(pin).unwrap().level == level);
        }
    }
    // PWM duty, as the pin toggles (timer 0's fast PWM: (raw + 1) / 256).
    for duty in [0.25, 0.75, 0.1] {
        AnalogOut::write(card.as_ref(), 1, duty).unwrap();
        let raw = (duty * 255.0_f64).round();
        let expect = (raw + 1.0) / 256.0;
        wait_until("the pin's duty", || {
            let p = sim.pin(6).unwrap();
            (p.duty - expect).abs() < 0.002 && p.period_us > 900.0
        });
    }
    // A servo's pulse (the Servo library's timer 1 interrupt drives the pin): 600 µs at
    // 0 degrees to 2400 µs at 180, every 20 ms.
    for (angle, pulse) in [(0.0, 600.0), (90.0, 1500.0), (180.0, 2400.0)] {
        AnalogOut::write(card.as_ref(), 2, angle).unwrap();
        wait_until("the servo's pulse", || {
            let p = sim.pin(9).unwrap();
            (p.duty * p.period_us - pulse).abs() < 20.0 && (p.period_us - 20_000.0).abs() < 500.0
        });
    }
    let c = card.counters();
    assert_eq!(
        (c.line.framing_errors, c.line.unknown_commands),
        (0, 0),
        "{c:?}"
    );
    // Settling at stop: sent, then confirmed pin by pin by the board; then no more writes.
    card.set_bit(3, false).unwrap();
    AnalogOut::write(card.as_ref(), 0, 0.0).unwrap();
    card.settle(std::time::Instant::now() + std::time::Duration::from_secs(5))
        .unwrap();
    assert!(!sim.pin(13).unwrap().level);
    assert!(matches!(card.set_bit(0, true), Err(DeviceError::Offline)));
    u.task.stop().unwrap();
}

#[test]
fn a_board_without_what_the_section_asks_is_refused_at_start() {
    let _one = one();
    let sim = SimUno::start().unwrap();
    let port = sim.pty().to_str().unwrap().to_string();
    let e = up(&port, "pwm = [{ pin = 2 }]").err().unwrap();
    assert!(
        e.contains("firmata.pwm[0].pin: pin 2 cannot be pwm: its modes are input, output, servo")
            && e.contains("pwm pins: 3, 5, 6, 9, 10, 11"),
        "{e}"
    );
    let e = up(&port, "analog_in = [{ channel = 6 }]").err().unwrap();
    assert!(
        e.contains("firmata.analog_in[0].channel: the board has no A6 (its analog channels: A0 (pin 14), A1 (pin 15)"),
        "{e}"
    );
    let e = up(&port, "analog_bits = 12\nanalog_in = [{ channel = 0 }]")
        .err()
        .unwrap();
    assert!(
        e.contains("pin 14 is analog in 10 bits on this board, not 12 bits"),
        "{e}"
    );
}

#[test]
fn unplugged_and_back_on_another_pty() {
    let _one = one();
    let dir = TempDir::new("firmata-replug");
    let link = dir.path().join("uno");
    let mut sim = SimUno::start().unwrap();
    std::os::unix::fs::symlink(sim.pty(), &link).unwrap();
    let u = up(link.to_str().unwrap(), PINS).unwrap();
    let card = u.card.clone();
    wait_until("the board online", || card.is_online());
    card.set_bit(1, true).unwrap();
    AnalogOut::write(card.as_ref(), 1, 0.25).unwrap();
    wait_until("pin 10 high", || sim.pin(10).unwrap().level);
    // The board comes back on another pty (the next board is started first, so the
    // kernel cannot hand it the number just freed; it is past its banner when found).
    let mut next = SimUno::start().unwrap();
    assert_ne!(sim.pty(), next.pty(), "a new pty");
    sim.kill();
    wait_until("the card offline", || !card.is_online());
    assert!(matches!(card.read_bit(0), Err(DeviceError::Offline)));
    std::mem::swap(&mut sim, &mut next);
    drop(next);
    std::fs::remove_file(&link).unwrap();
    std::os::unix::fs::symlink(sim.pty(), &link).unwrap();
    wait_until("the card back online", || card.is_online());
    // Its modes and outputs restored, its inputs reported.
    wait_until("pin 10 high again", || sim.pin(10).unwrap().level);
    let p = sim.pin(6).unwrap();
    assert!(p.output, "{p:?}");
    wait_until("pwm restored", || {
        (sim.pin(6).unwrap().duty - 65.0 / 256.0).abs() < 0.002
    });
    sim.input(3, true).unwrap();
    wait_until("input 3", || card.read_bit(1).ok() == Some(true));
    let c = card.counters();
    assert!(c.reopens >= 1 && c.opens >= 2, "{c:?}");
    u.task.stop().unwrap();
}

#[test]
fn garbage_and_truncated_frames_are_counted_and_decoding_goes_on() {
    let _one = one();
    let mut sim = SimUno::start().unwrap();
    let u = up(sim.pty().to_str().unwrap(), PINS).unwrap();
    let card = u.card.clone();
    wait_until("the board online", || card.is_online());
    let before = card.counters().line;
    // Stray data bytes; an analog message cut short by a command byte; commands a board
    // does not send; an unknown sysex; an empty sysex; a sysex far too long.
    sim.inject(&[0x12, 0x34, 0x56]).unwrap();
    sim.inject(&[0xE0, 0x05]).unwrap();
    sim.inject(&[0xA5, 0x01, 0xF4, 0x02, 0x01]).unwrap();
    sim.inject(&[0xF0, 0x55, 0x01, 0x02, 0xF7, 0xF0, 0xF7])
        .unwrap();
    sim.inject(&[0xF0, 0x71]).unwrap();
    for _ in 0..5 {
        sim.inject(&[0x41; 1000]).unwrap();
    }
    sim.inject(&[0xF7]).unwrap();
    wait_until("the garbage counted", || {
        let l = card.counters().line;
        l.framing_errors >= before.framing_errors + 6
            && l.unknown_commands >= before.unknown_commands + 3
            && l.resyncs >= before.resyncs + 4
    });
    // Still decoding: a new analog value and a new input level come through.
    sim.adc(1, 3000).unwrap();
    wait_until("A1 after the garbage", || {
        card.read_raw(1).ok() == Some(613)
    });
    sim.input(7, true).unwrap();
    wait_until("input 7 after the garbage", || {
        card.read_bit(3).ok() == Some(true)
    });
    assert!(card.is_online());
    u.task.stop().unwrap();
}

#[test]
fn conformance_kit_over_the_cards_interfaces() {
    let _one = one();
    let sim = Mutex::new(SimUno::start().unwrap());
    let port = sim.lock().unwrap().pty().to_str().unwrap().to_string();
    let u = up(&port, PINS).unwrap();
    let card = u.card.clone();
    wait_until("the board online", || card.is_online());
    let channels = [0u8, 1, 5];
    let mut ai = |ch: u32, raw: i64| {
        let c = channels[ch as usize];
        sim.lock()
            .unwrap()
            .adc(c, millivolts_for(raw as u16))
            .unwrap();
        wait_until("the injected value", || card.read_raw(ch).ok() == Some(raw));
    };
    conformance::check_analog_in(card.as_ref(), Some(&mut ai)).assert_complete();
    conformance::check_analog_out(card.as_ref()).assert_complete();
    let pins = [2u8, 3, 4, 7];
    let mut di = |bit: u32, on: bool| {
        sim.lock().unwrap().input(pins[bit as usize], on).unwrap();
        wait_until("the driven level", || card.read_bit(bit).ok() == Some(on));
    };
    conformance::check_digital_in(card.as_ref(), Some(&mut di)).assert_complete();
    conformance::check_digital_out(card.as_ref()).assert_complete();
    // What the kit left on the outputs reached the pins.
    for (bit, pin) in [8u8, 10, 12, 13].into_iter().enumerate() {
        let want = card.check_bit(bit as u32).unwrap();
        wait_until("the outputs as the kit left them", || {
            sim.lock().unwrap().pin(pin).unwrap().level == want
        });
    }
    u.task.stop().unwrap();
}
