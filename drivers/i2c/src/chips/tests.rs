//! The chip models on a register file with i2c-stub's model, for what the kernel tests
//! cannot make happen on cue: a conversion that does not finish, a chip found reset, a
//! chip probed again.
#![allow(clippy::unwrap_used, reason = "test code")]

use super::{ChipError, ChipModel, Lost, Outcome, model, place};
use crate::card::I2cCard;
use crate::config::{ChipConfig, I2cConfig};
use crate::smbus::fake::Registers;
use crate::smbus::{Smbus, Transfer};
use device_interface::time::{SimClock, Timestamp};
use device_interface::{AnalogIn, AnalogOut, DeviceError};
use std::sync::Arc;
use std::time::Duration;

/// The model of one `[[chip]]` table, its card (on a clock the test moves) and a register
/// file.
fn chip(table: &str) -> (Box<dyn ChipModel>, Arc<I2cCard>, Registers, Arc<SimClock>) {
    let config: I2cConfig =
        toml::from_str(&format!("bus = \"/dev/i2c-0\"\n[[chip]]\n{table}")).unwrap();
    config.check().unwrap();
    let m = model(&config.chip[0]);
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(0)));
    let card = one_chip_on(&config.chip[0], m.as_ref(), clock.clone());
    (m, card, Registers::new(), clock)
}

fn start(
    m: &mut Box<dyn ChipModel>,
    card: &I2cCard,
    chip: &mut dyn Smbus,
) -> Result<Outcome, ChipError> {
    m.start(chip, &card.io(0).unwrap())
}

fn poll(
    m: &mut Box<dyn ChipModel>,
    card: &I2cCard,
    chip: &mut dyn Smbus,
) -> Result<Outcome, ChipError> {
    m.poll(chip, &card.io(0).unwrap())
}

fn check(m: &mut Box<dyn ChipModel>, card: &I2cCard, regs: &Registers) -> Option<Lost> {
    m.check(&mut regs.clone() as &mut dyn Smbus, &card.io(0).unwrap())
        .unwrap()
}

fn online(card: &I2cCard) {
    card.chips()[0]
        .online
        .store(true, std::sync::atomic::Ordering::Release);
}

/// The datasheet's word as an SMBus word of a big-endian register.
fn be(word: u16) -> u16 {
    word.swap_bytes()
}

const ADS_SLOW: &str = "model = \"ads1115\"\naddress = 0x48\npoll_ms = 5\ndata_rate = 8\n\
    channel = [{ input = \"a0\", range_v = 4.096 }, { input = \"a1\", range_v = 4.096 }]";
/// Channel 0's config word: OS | MUX a0 | PGA ±4.096 V | single-shot | 8/s | COMP_LAT |
/// comparator off.
const A0: u16 = 0xc307;
const A1: u16 = 0xd307;
/// A conversion at 8/s takes at most 137.5 ms; it is given twice that and 1 ms.
const ADS_DEADLINE: Duration = Duration::from_micros(276_000);

#[test]
fn ads1115_waits_for_a_conversion_and_a_stuck_one_fails_each_deadline_without_a_restart() {
    let (mut m, card, mut regs, clock) = chip(ADS_SLOW);
    online(&card);
    assert_eq!(start(&mut m, &card, &mut regs), Ok(Outcome::Pending));
    assert_eq!(regs.writes(), [(0x01, be(A0))], "channel 0 started");
    // The chip clears OS while it converts.
    regs.set(0x01, be(A0 & 0x7fff));
    regs.set(0x00, be(0x1234));
    clock.advance(ADS_DEADLINE - Duration::from_micros(1));
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Pending));
    assert!(matches!(card.read_raw(0), Err(DeviceError::Stale { .. })));
    clock.advance(Duration::from_micros(1));
    let e = poll(&mut m, &card, &mut regs).unwrap_err();
    assert_eq!(
        e.to_string(),
        "channel 0's conversion not done within 276000 µs (one takes at most 137500 µs; OS \
         stays 0): the chip is not converting"
    );
    // Counted once: the next poll waits a whole deadline again before it fails another.
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Pending));
    clock.advance(ADS_DEADLINE);
    assert!(matches!(
        poll(&mut m, &card, &mut regs),
        Err(ChipError::NotConverting { .. })
    ));
    // Never started again (OS written during a conversion does nothing), nothing read.
    assert!(regs.writes().is_empty());
    assert!(matches!(card.read_raw(0), Err(DeviceError::Stale { .. })));
    // A probe of the stuck chip finds our conversion under way and waits on it.
    assert_eq!(start(&mut m, &card, &mut regs), Ok(Outcome::Pending));
    assert!(
        regs.writes().is_empty(),
        "a conversion under way left alone"
    );
    // Done: read, and the next channel started.
    regs.set(0x01, be(A0));
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Fresh));
    assert_eq!(card.read_raw(0).unwrap(), 0x1234);
    assert_eq!(regs.writes(), [(0x01, be(A1))]);
}

#[test]
fn ads1115_found_reset_publishes_nothing_and_converts_the_same_channel_again() {
    let (mut m, card, mut regs, _clock) = chip(ADS_SLOW);
    online(&card);
    start(&mut m, &card, &mut regs).unwrap();
    regs.set(0x00, be(0x1234));
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Fresh));
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Fresh));
    regs.writes();
    // A brown-out while channel 0 converts: Config and Conversion at their power-on values.
    regs.set(0x01, be(super::ads1115::POWER_ON));
    regs.set(0x00, 0);
    let lost = Lost {
        register: "config",
        found: 0x8583,
        wanted: A0,
    };
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Reset(lost)));
    assert_eq!(lost.to_string(), "config reads 0x8583, not 0xc307");
    assert_eq!(card.read_raw(0).unwrap(), 0x1234, "the 0 not published");
    assert!(regs.writes().is_empty(), "nothing written by the poll");
    // Set up again (the bus side calls start): channel 0 started again, then read.
    assert_eq!(start(&mut m, &card, &mut regs), Ok(Outcome::Pending));
    assert_eq!(regs.writes(), [(0x01, be(A0))]);
    regs.set(0x00, be(0x0777));
    assert_eq!(poll(&mut m, &card, &mut regs), Ok(Outcome::Fresh));
    assert_eq!(card.read_raw(0).unwrap(), 0x0777);
}

/// A chip that resets as its Conversion register is read (between the poll's two reads).
struct ResetsOnRead(Registers);

impl Smbus for ResetsOnRead {
    fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer> {
        self.0.read_byte(reg)
    }
    fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer> {
        self.0.write_byte(reg, value)
    }
    fn read_word(&mut self, reg: u8) -> Result<u16, Transfer> {
        if reg == 0x00 {
            self.0.set(0x00, 0);
            self.0.set(0x01, be(super::ads1115::POWER_ON));
        }
        self.0.read_word(reg)
    }
    fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer> {
        self.0.write_word(reg, value)
    }
}

#[test]
fn ads1115_reads_config_again_after_a_zero_result() {
    let (mut m, card, regs, _clock) = chip(ADS_SLOW);
    online(&card);
    start(&mut m, &card, &mut regs.clone()).unwrap();
    let mut chip = ResetsOnRead(regs.clone());
    assert!(matches!(
        poll(&mut m, &card, &mut chip),
        Ok(Outcome::Reset(Lost { found: 0x8583, .. }))
    ));
    assert!(matches!(card.read_raw(0), Err(DeviceError::Stale { .. })));
}

#[test]
fn ads1115_never_writes_its_power_on_config() {
    // a0-a1 at ±2.048 V and 128/s is the power-on setting: COMP_LAT tells them apart.
    let (mut m, card, mut regs, _clock) = chip(
        "model = \"ads1115\"\naddress = 0x48\ndata_rate = 128\n\
         channel = [{ input = \"a0-a1\", range_v = 2.048 }]",
    );
    start(&mut m, &card, &mut regs).unwrap();
    assert_eq!(regs.writes(), [(0x01, be(0x8587))]);
}

/// An INA219 as far as CNVR goes: reading Power clears it.
#[derive(Clone)]
pub(crate) struct Ina219Chip(pub(crate) Registers);

impl Smbus for Ina219Chip {
    fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer> {
        self.0.read_byte(reg)
    }
    fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer> {
        self.0.write_byte(reg, value)
    }
    fn read_word(&mut self, reg: u8) -> Result<u16, Transfer> {
        let word = self.0.read_word(reg);
        if reg == 0x03 {
            self.0
                .set(0x02, self.0.get(0x02) & !be(super::ina219::CNVR));
        }
        word
    }
    fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer> {
        self.0.write_word(reg, value)
    }
}

const INA: &str = "model = \"ina219\"\naddress = 0x40\nshunt_ohms = 0.1\nmax_current_a = 3.2";

/// The chip converted: shunt 1000, bus 3000 (and CNVR), current `current` counts.
pub(crate) fn converted(regs: &Registers, current: i16) {
    regs.set(0x01, be(1000));
    regs.set(0x04, be(current as u16));
    regs.set(0x02, be(3000 << 3 | super::ina219::CNVR));
}

#[test]
fn ina219_publishes_nothing_read_with_a_lost_calibration_nor_before_a_conversion_with_it() {
    let (mut m, card, regs, _clock) = chip(INA);
    let mut ina = Ina219Chip(regs.clone());
    online(&card);
    converted(&regs, 2000);
    // Set up: configuration, calibration, Power read (CNVR cleared): nothing published until
    // a conversion finishes.
    assert_eq!(start(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    assert_eq!(regs.writes(), [(0x00, be(0x399f)), (0x05, be(0x1062))]);
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    assert!(matches!(card.read_raw(2), Err(DeviceError::Stale { .. })));
    converted(&regs, 2000);
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Fresh));
    assert_eq!(
        (0..3)
            .map(|c| card.read_raw(c).unwrap())
            .collect::<Vec<_>>(),
        [1000, 3000, 2000]
    );
    // A brown-out: calibration 0, so the current reads 0 (shunt and bus go on).
    regs.set(0x05, 0);
    regs.set(0x04, 0);
    let lost = Lost {
        register: "calibration",
        found: 0,
        wanted: 0x1062,
    };
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Reset(lost)));
    assert_eq!(card.read_raw(2).unwrap(), 2000, "the 0 not published");
    // Set up again; the current register still holds the 0 worked out before: not
    // published until the chip has converted with the calibration.
    assert_eq!(start(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    assert_eq!(regs.get(0x05), be(0x1062));
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    assert_eq!(card.read_raw(2).unwrap(), 2000);
    converted(&regs, 1999);
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Fresh));
    assert_eq!(card.read_raw(2).unwrap(), 1999);
    // Polls after the first conversion do not need CNVR again.
    regs.set(0x02, be(3001 << 3));
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Fresh));
    assert_eq!(card.read_raw(1).unwrap(), 3001);
    // Another master's configuration is the check's to find.
    assert_eq!(check(&mut m, &card, &regs), None);
    regs.set(0x00, be(0x019f));
    assert_eq!(
        check(&mut m, &card, &regs).map(|l| l.to_string()),
        Some("configuration reads 0x019f, not 0x399f".into())
    );
}

#[test]
fn ina219_not_converting_after_a_set_up_fails_each_deadline() {
    let (mut m, card, regs, clock) = chip(INA);
    let mut ina = Ina219Chip(regs.clone());
    converted(&regs, 5);
    start(&mut m, &card, &mut ina).unwrap();
    // 12-bit shunt and bus: 1172 µs at most; given twice that and 1 ms.
    clock.advance(Duration::from_micros(3343));
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    clock.advance(Duration::from_micros(1));
    let e = poll(&mut m, &card, &mut ina).unwrap_err();
    assert_eq!(
        e.to_string(),
        "a conversion not done within 3344 µs (one takes at most 1172 µs; CNVR stays 0 \
         since hwgw set the chip up): the chip is not converting"
    );
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Pending));
    converted(&regs, 5);
    assert_eq!(poll(&mut m, &card, &mut ina), Ok(Outcome::Fresh));
}

#[test]
fn mcp23017_sets_iocon_first_and_its_check_finds_a_reset() {
    let (mut m, card, mut regs, _) =
        chip("model = \"mcp23017\"\naddress = 0x20\ninputs = [3]\noutputs = [0, 9]\npull_up = [3]");
    start(&mut m, &card, &mut regs).unwrap();
    let writes = regs.writes();
    assert_eq!(
        writes[..2],
        [(0x05, 0), (0x0a, 0)],
        "IOCON first: {writes:x?}"
    );
    assert_eq!(writes[2].0, 0x14, "then the latch: {writes:x?}");
    assert_eq!(check(&mut m, &card, &regs), None);
    // A power-on reset: all inputs, no pull-ups.
    regs.set(0x00, 0xffff);
    regs.set(0x0c, 0);
    assert_eq!(
        check(&mut m, &card, &regs).map(|l| l.to_string()),
        Some("IODIR reads 0xffff, not 0xfdfe".into())
    );
    start(&mut m, &card, &mut regs).unwrap();
    assert_eq!(regs.get(0x00), !0x0201, "IODIR again");
    assert_eq!(check(&mut m, &card, &regs), None);
}

#[test]
fn pca9685_sleeps_only_to_change_its_prescale_and_keeps_mode1s_other_bits() {
    let (mut m, card, mut regs, _) =
        chip("model = \"pca9685\"\naddress = 0x41\nfrequency_hz = 1000\nchannels = [0]");
    // Power-on: ALLCALL, asleep, prescale 30 (200 Hz).
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    start(&mut m, &card, &mut regs).unwrap();
    let writes = regs.writes();
    assert_eq!(writes[..2], [(0x00, 0x31), (0xfe, 5)], "{writes:x?}");
    assert_eq!(writes.last(), Some(&(0x00, 0x21)), "awake, ALLCALL kept");
    assert_eq!(check(&mut m, &card, &regs), None);
    // Probed again (a dropout, the chip still set up): never put to sleep.
    online(&card);
    card.write_raw(0, 2048).unwrap();
    start(&mut m, &card, &mut regs).unwrap();
    let writes = regs.writes();
    assert!(
        writes.iter().all(|(reg, _)| *reg != 0x00 && *reg != 0xfe),
        "{writes:x?}"
    );
    assert_eq!(regs.get(0x08), 2048);
    // After a power loss: asleep at the default prescale, found and set up again.
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    assert_eq!(
        check(&mut m, &card, &regs).map(|l| l.to_string()),
        Some("MODE1 reads 0x0011, not 0x0021".into())
    );
    start(&mut m, &card, &mut regs).unwrap();
    assert_eq!(
        (regs.get(0x00), regs.get(0xfe), regs.get(0x08)),
        (0x21, 5, 2048)
    );
}

#[test]
fn pca9685_at_its_power_on_prescale_sets_auto_increment_before_the_duty_words() {
    // 200 Hz: prescale 30, the power-on value, so it need not sleep to set it.
    let (mut m, card, mut regs, _) =
        chip("model = \"pca9685\"\naddress = 0x41\nfrequency_hz = 200\nchannels = [0]");
    regs.set(0x00, 0x11);
    regs.set(0xfe, 30);
    start(&mut m, &card, &mut regs).unwrap();
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
    let (mut m, card, mut regs, _) = chip("model = \"mcp4725\"\naddress = 0x60\nvref_v = 5.0");
    online(&card);
    card.write_raw(0, 0xa8f).unwrap();
    poll(&mut m, &card, &mut regs).unwrap();
    assert_eq!(regs.writes(), [(0x0a, 0x8f)]);
    poll(&mut m, &card, &mut regs).unwrap();
    assert!(regs.writes().is_empty(), "a poll sends only a change");
    assert_eq!(check(&mut m, &card, &regs), None);
    assert_eq!(regs.writes(), [(0x0a, 0x8f)]);
}

#[test]
fn as5600_keeps_a_homed_position_across_a_dropout() {
    let (mut m, card, mut regs, _) = chip("model = \"as5600\"\naddress = 0x36");
    regs.set(0x0b, 0x20);
    regs.set(0x0c, 1000u16.swap_bytes());
    start(&mut m, &card, &mut regs).unwrap();
    let io = card.io(0).unwrap();
    let counter = io.encoder(0).unwrap();
    assert_eq!(counter.position(), 1000);
    // Homed here.
    counter.set_position(0).unwrap();
    regs.set(0x0c, 1100u16.swap_bytes());
    poll(&mut m, &card, &mut regs).unwrap();
    assert_eq!(counter.position(), 100);
    // It stops answering, moves on while it does not, and is probed again.
    regs.set(0x0c, 1300u16.swap_bytes());
    start(&mut m, &card, &mut regs).unwrap();
    assert_eq!(counter.position(), 300, "the homing kept");
}

/// A card of the one chip `config` describes, for unit tests, on a simulated clock at 0.
pub(crate) fn one_chip(config: &ChipConfig, model: &dyn ChipModel) -> Arc<I2cCard> {
    one_chip_on(
        config,
        model,
        Arc::new(SimClock::new(Timestamp::from_nanos(0))),
    )
}

/// The same on `clock`.
pub(crate) fn one_chip_on(
    config: &ChipConfig,
    model: &dyn ChipModel,
    clock: Arc<SimClock>,
) -> Arc<I2cCard> {
    match I2cCard::new(&[place(config, model)], clock) {
        Ok(card) => Arc::new(card),
        Err(e) => panic!("a test card: {e}"),
    }
}
