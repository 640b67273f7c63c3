//! The chip models on a register file with i2c-stub's model, for what the kernel tests
//! cannot make happen on cue: a conversion that does not finish, a chip found reset, a
//! chip probed again.
#![allow(clippy::unwrap_used, reason = "test code")]

use super::{ChipModel, model, place};
use crate::card::I2cCard;
use crate::config::{ChipConfig, I2cConfig};
use crate::smbus::fake::Registers;
use crate::smbus::{Smbus, Transfer};
use device_interface::{AnalogIn, AnalogOut, DeviceError};
use std::sync::Arc;

/// The model of one `[[chip]]` table, its card and a register file.
fn chip(table: &str) -> (Box<dyn ChipModel>, Arc<I2cCard>, Registers) {
    let config: I2cConfig =
        toml::from_str(&format!("bus = \"/dev/i2c-0\"\n[[chip]]\n{table}")).unwrap();
    config.check().unwrap();
    let m = model(&config.chip[0]);
    let card = one_chip(&config.chip[0], m.as_ref());
    (m, card, Registers::new())
}

fn start(m: &mut Box<dyn ChipModel>, card: &I2cCard, regs: &Registers) -> Result<(), Transfer> {
    m.start(&mut regs.clone() as &mut dyn Smbus, &card.io(0).unwrap())
}

fn poll(m: &mut Box<dyn ChipModel>, card: &I2cCard, regs: &Registers) -> Result<(), Transfer> {
    m.poll(&mut regs.clone() as &mut dyn Smbus, &card.io(0).unwrap())
}

fn check(m: &mut Box<dyn ChipModel>, card: &I2cCard, regs: &Registers) -> bool {
    m.check(&mut regs.clone() as &mut dyn Smbus, &card.io(0).unwrap())
        .unwrap()
}

fn online(card: &I2cCard) {
    card.chips()[0]
        .online
        .store(true, std::sync::atomic::Ordering::Release);
}

#[test]
fn ads1115_waits_for_a_slow_conversion_then_counts_it_failed_and_starts_it_again() {
    // 8 conversions/s polled every 5 ms: 125 ms a conversion, patience 2 × 25 + 1 polls.
    let (mut m, card, regs) = chip(
        "model = \"ads1115\"\naddress = 0x48\npoll_ms = 5\ndata_rate = 8\n\
         channel = [{ input = \"a0\", range_v = 4.096 }]",
    );
    online(&card);
    start(&mut m, &card, &regs).unwrap();
    let config = regs.get(0x01).swap_bytes();
    assert_eq!(config & 0x8000, 0x8000, "OS written: a conversion started");
    regs.writes();
    // The chip clears OS while it converts.
    regs.set(0x01, (config & 0x7fff).swap_bytes());
    regs.set(0x00, 0x1234u16.swap_bytes());
    for i in 0..50 {
        poll(&mut m, &card, &regs).unwrap_or_else(|e| panic!("poll {i}: {e}"));
        assert!(matches!(card.read_raw(0), Err(DeviceError::Stale { .. })));
    }
    assert!(
        regs.writes().is_empty(),
        "nothing started while it converts"
    );
    let e = poll(&mut m, &card, &regs).unwrap_err();
    assert!(e.to_string().contains("not done after 51 polls"), "{e}");
    assert_eq!(
        regs.writes(),
        [(0x01, config.swap_bytes())],
        "started again"
    );
    // Done (OS set again by the write): read, and the next one started.
    poll(&mut m, &card, &regs).unwrap();
    assert_eq!(card.read_raw(0).unwrap(), 0x1234);
}

#[test]
fn mcp23017_sets_iocon_first_and_its_check_finds_a_reset() {
    let (mut m, card, regs) =
        chip("model = \"mcp23017\"\naddress = 0x20\ninputs = [3]\noutputs = [0, 9]\npull_up = [3]");
    start(&mut m, &card, &regs).unwrap();
    let writes = regs.writes();
    assert_eq!(
        writes[..2],
        [(0x05, 0), (0x0a, 0)],
        "IOCON first: {writes:x?}"
    );
    assert_eq!(writes[2].0, 0x14, "then the latch: {writes:x?}");
    assert!(check(&mut m, &card, &regs));
    // A power-on reset: all inputs, no pull-ups.
    regs.set(0x00, 0xffff);
    regs.set(0x0c, 0);
    assert!(!check(&mut m, &card, &regs));
    start(&mut m, &card, &regs).unwrap();
    assert_eq!(regs.get(0x00), !0x0201, "IODIR again");
    assert!(check(&mut m, &card, &regs));
}

#[test]
fn pca9685_sleeps_only_to_change_its_prescale_and_keeps_mode1s_other_bits() {
    let (mut m, card, regs) =
        chip("model = \"pca9685\"\naddress = 0x41\nfrequency_hz = 1000\nchannels = [0]");
    // Power-on: ALLCALL, asleep, prescale 30 (200 Hz).
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    start(&mut m, &card, &regs).unwrap();
    let writes = regs.writes();
    assert_eq!(writes[..2], [(0x00, 0x31), (0xfe, 5)], "{writes:x?}");
    assert_eq!(writes.last(), Some(&(0x00, 0x21)), "awake, ALLCALL kept");
    assert!(check(&mut m, &card, &regs));
    // Probed again (a dropout, the chip still set up): never put to sleep.
    online(&card);
    card.write_raw(0, 2048).unwrap();
    start(&mut m, &card, &regs).unwrap();
    let writes = regs.writes();
    assert!(
        writes.iter().all(|(reg, _)| *reg != 0x00 && *reg != 0xfe),
        "{writes:x?}"
    );
    assert_eq!(regs.get(0x08), 2048);
    // After a power loss: asleep at the default prescale, found and set up again.
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    assert!(!check(&mut m, &card, &regs));
    start(&mut m, &card, &regs).unwrap();
    assert_eq!(
        (regs.get(0x00), regs.get(0xfe), regs.get(0x08)),
        (0x21, 5, 2048)
    );
}

#[test]
fn pca9685_at_its_power_on_prescale_sets_auto_increment_before_the_duty_words() {
    // 200 Hz: prescale 30, the power-on value, so it need not sleep to set it.
    let (mut m, card, regs) =
        chip("model = \"pca9685\"\naddress = 0x41\nfrequency_hz = 200\nchannels = [0]");
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    start(&mut m, &card, &regs).unwrap();
    let writes = regs.writes();
    assert_eq!(
        writes[0],
        (0x00, 0x31),
        "AI first, still asleep: {writes:x?}"
    );
    assert!(writes[1..].iter().all(|w| w.0 != 0xfe), "{writes:x?}");
    assert_eq!(
        writes.last(),
        Some(&(0x00, 0x21)),
        "then awake: {writes:x?}"
    );
}

#[test]
fn mcp4725_check_sends_the_asked_code_again() {
    let (mut m, card, regs) = chip("model = \"mcp4725\"\naddress = 0x60\nvref_v = 5.0");
    online(&card);
    card.write_raw(0, 0xa8f).unwrap();
    poll(&mut m, &card, &regs).unwrap();
    assert_eq!(regs.writes(), [(0x0a, 0x8f)]);
    poll(&mut m, &card, &regs).unwrap();
    assert!(regs.writes().is_empty(), "a poll sends only a change");
    assert!(check(&mut m, &card, &regs));
    assert_eq!(regs.writes(), [(0x0a, 0x8f)]);
}

#[test]
fn ina219_check_finds_a_lost_calibration() {
    let (mut m, card, regs) =
        chip("model = \"ina219\"\naddress = 0x40\nshunt_ohms = 0.1\nmax_current_a = 3.2");
    start(&mut m, &card, &regs).unwrap();
    assert!(check(&mut m, &card, &regs));
    // A power-on reset: the configuration is the default (the one hwgw writes), the
    // calibration 0.
    regs.set(0x05, 0);
    assert!(!check(&mut m, &card, &regs));
}

#[test]
fn as5600_keeps_a_homed_position_across_a_dropout() {
    let (mut m, card, regs) = chip("model = \"as5600\"\naddress = 0x36");
    regs.set(0x0b, 0x20);
    regs.set(0x0c, 1000u16.swap_bytes());
    start(&mut m, &card, &regs).unwrap();
    let io = card.io(0).unwrap();
    let counter = io.encoder(0).unwrap();
    assert_eq!(counter.position(), 1000);
    // Homed here.
    counter.set_position(0).unwrap();
    regs.set(0x0c, 1100u16.swap_bytes());
    poll(&mut m, &card, &regs).unwrap();
    assert_eq!(counter.position(), 100);
    // It stops answering, moves on while it does not, and is probed again.
    regs.set(0x0c, 1300u16.swap_bytes());
    start(&mut m, &card, &regs).unwrap();
    assert_eq!(counter.position(), 300, "the homing kept");
}

/// A card of the one chip `config` describes, for unit tests, on a simulated clock at 0.
pub(crate) fn one_chip(config: &ChipConfig, model: &dyn ChipModel) -> Arc<I2cCard> {
    let clock =
        device_interface::time::SimClock::new(device_interface::time::Timestamp::from_nanos(0));
    match I2cCard::new(&[place(config, model)], Arc::new(clock)) {
        Ok(card) => Arc::new(card),
        Err(e) => panic!("a test card: {e}"),
    }
}
