//! The I2C card against the real kernel: the i2c-stub bus in the kernel rig, chips' input
//! registers set and output registers read back with i2c-tools (the independent peer).
#![allow(clippy::unwrap_used, reason = "test code")]

use device_interface::conformance;
use device_interface::time::MonotonicClock;
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut};
use driver_i2c::card::I2cCard;
use driver_i2c::component::I2cIo;
use driver_i2c::config::I2cConfig;
use kernel_rig::{Failed, Trial};
use rtt::{Runtime, RuntimeOptions};
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::{I2cStub, wait_for};

const PATIENCE: Duration = Duration::from_secs(10);

/// A card of `chips` (TOML `[[chip]]` tables) on `stub`, its bus component running.
struct Up {
    card: Arc<I2cCard>,
    task: rtt::TaskContext,
    _rt: Runtime,
}

fn up(stub: &I2cStub, chips: &str) -> Result<Up, Failed> {
    let config: I2cConfig = toml::from_str(&format!(
        "bus = {:?}\n{chips}",
        stub.path().display().to_string()
    ))?;
    let built = driver_i2c::plugin::card(&config, Arc::new(MonotonicClock))
        .map_err(|e| Failed::from(format!("{}: {}", e.key.unwrap_or_default(), e.message)))?;
    let card = built.card.clone();
    let rt = Runtime::new(
        Arc::new(device_interface::Registry::new()),
        RuntimeOptions::default(),
    )?;
    let task = I2cIo::add(&rt, "i2c", built.bus(), Default::default())?;
    task.start()?;
    Ok(Up {
        card,
        task,
        _rt: rt,
    })
}

fn wait(what: &str, f: impl FnMut() -> bool) -> Result<(), Failed> {
    wait_for(what, PATIENCE, f).map_err(Failed::from)
}

const MCP: &str = r#"
[[chip]]
model = "mcp23017"
address = 0x20
poll_ms = 5
inputs = [8, 9, 3]
pull_up = [8]
invert = [9]
outputs = [0, 1, 15]
initial_on = [1]
"#;

fn mcp23017_registers_as_i2c_tools_sees_them() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20])?;
    // GPB0 (pin 8) and GPA3 high before hwgw starts.
    stub.set_word(0x20, 0x12, 0x0108)?;
    let up = up(&stub, MCP)?;
    let c = &*up.card;
    wait("the chip online", || c.counters().chips[0].online)?;
    // Configured as the section says, one word per A/B register pair.
    assert_eq!(
        stub.get_word(0x20, 0x00)?,
        !0x8003u16,
        "IODIR: pins 0, 1, 15 outputs"
    );
    assert_eq!(stub.get_word(0x20, 0x02)?, 0x0200, "IPOL: pin 9 inverted");
    assert_eq!(stub.get_word(0x20, 0x0c)?, 0x0100, "GPPU: pin 8 pulled up");
    assert_eq!(
        stub.get_word(0x20, 0x14)?,
        0x0002,
        "OLAT: pin 1 on from the start"
    );
    assert_eq!(
        (c.read_bit(0)?, c.read_bit(1)?, c.read_bit(2)?),
        (true, false, true)
    );
    // i2c-stub does not apply IPOL: what GPIO holds is what the card reads.
    stub.set_word(0x20, 0x12, 0x0200)?;
    wait("inputs follow GPIO", || {
        (c.read_bit(0).ok(), c.read_bit(1).ok(), c.read_bit(2).ok())
            == (Some(false), Some(true), Some(false))
    })?;
    c.set_bit(2, true)?;
    c.set_bit(1, false)?;
    wait("OLAT follows the writes", || {
        stub.get_word(0x20, 0x14).ok() == Some(0x8000)
    })?;
    assert!(c.check_bit(2)? && !c.check_bit(1)?);
    Ok(())
}

fn a_chip_that_does_not_answer_is_offline_and_others_keep_polling() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20])?;
    let up = up(
        &stub,
        r#"
[[chip]]
model = "mcp23017"
address = 0x20
poll_ms = 5
inputs = [0]
[[chip]]
model = "mcp23017"
address = 0x21
poll_ms = 5
outputs = [0]
initial_on = [0]
"#,
    )?;
    let c = up.card.clone();
    wait("0x20 online, 0x21 refused", || {
        c.counters().chips[0].online && c.counters().chips[1].last_error.is_some()
    })?;
    let dead = c.counters().chips[1].clone();
    assert!(!dead.online, "{dead:?}");
    let why = dead.last_error.unwrap_or_default();
    assert!(why.contains("no answer"), "{why}");
    assert!(matches!(c.set_bit(0, false), Err(DeviceError::Offline)));
    assert!(c.read_bit(0).is_ok());
    // The live chip's poll rate beside the dead one (reported, not asserted: the rig is
    // a shared machine).
    let (p0, t0) = (c.counters().chips[0].polls, Instant::now());
    wait("100 more polls of 0x20", || {
        c.counters().chips[0].polls >= p0 + 100
    })?;
    let rate = (c.counters().chips[0].polls - p0) as f64 / t0.elapsed().as_secs_f64();
    println!("0x20 polled at {rate:.0}/s (period 5 ms: 200/s) beside a dead 0x21");
    // Probed with a backoff all along: its failures keep coming, slower and slower.
    let errors = c.counters().chips[1].errors;
    assert!(errors >= 2, "{errors} probes");
    // i2c-stub gets its chips only when loaded, and an open bus file pins the module: the
    // bus component stops (closing the bus), the stub comes back with 0x21, and the
    // component starts again — probing 0x21, configuring it, writing its output as asked.
    let bus = stub.bus;
    up.task.stop()?;
    drop(stub);
    let stub = I2cStub::load(&[0x20, 0x21])?;
    assert_eq!(stub.bus, bus, "the stub came back as another adapter");
    up.task.start()?;
    wait("0x21 online", || c.counters().chips[1].online)?;
    assert_eq!(stub.get_word(0x21, 0x14)?, 0x0001, "OLAT as asked");
    assert_eq!(stub.get_word(0x21, 0x00)?, 0xfffe, "IODIR");
    assert!(c.counters().chips[0].online);
    Ok(())
}

fn the_conformance_kit_passes() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20])?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"mcp23017\"\naddress = 0x20\npoll_ms = 2\ninputs = [4, 12]\noutputs = [2, 7]",
    )?;
    let c = up.card.clone();
    wait("online", || c.counters().chips[0].online)?;
    let gpio = std::cell::Cell::new(0u16);
    let mut set_di = |b: u32, v: bool| {
        let pin = [4, 12][b as usize];
        let word = if v {
            gpio.get() | 1 << pin
        } else {
            gpio.get() & !(1 << pin)
        };
        gpio.set(word);
        stub.set_word(0x20, 0x12, word).unwrap();
        wait_for("the input follows", PATIENCE, || {
            c.read_bit(b).ok() == Some(v)
        })
        .unwrap();
    };
    // Through the devices the card registers, as a user gets them.
    let devices = up.card.devices();
    let (di, dout) = (devices.digital_in.unwrap(), devices.digital_out.unwrap());
    assert!(devices.analog_in.is_none());
    conformance::check_digital_in(&*di, Some(&mut set_di)).assert_complete();
    conformance::check_digital_out(&*dout).assert_complete();
    drop(up);
    drop(stub);
    let stub = I2cStub::load(&[0x48])?;
    let adc = self::up(&stub, ADS)?;
    let c = adc.card.clone();
    wait("converted", || c.read_raw(2).is_ok())?;
    let mut set_ai = |ch: u32, raw: i64| {
        stub.set_word(0x48, 0x00, wire(raw as i16)).unwrap();
        wait_for("the channel follows", PATIENCE, || {
            c.read_raw(ch).ok() == Some(raw)
        })
        .unwrap();
    };
    let ai = adc.card.devices().analog_in.unwrap();
    conformance::check_analog_in(&*ai, Some(&mut set_ai)).assert_complete();
    Ok(())
}

const ADS: &str = r#"
[[chip]]
model = "ads1115"
address = 0x48
poll_ms = 2
channel = [
    { input = "a0", range_v = 4.096 },
    { input = "a0-a1", range_v = 0.256 },
    { input = "a3", range_v = 6.144 },
]
"#;

/// `raw` as the ADS1115 sends it (MSB first) read as an SMBus word (LSB first).
fn wire(raw: i16) -> u16 {
    (raw as u16).swap_bytes()
}

fn ads1115_converts_with_each_range_and_sign() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x48])?;
    stub.set_word(0x48, 0x00, wire(16384))?;
    let up = up(&stub, ADS)?;
    let c = &*up.card;
    wait("all three converted", || {
        (0..3).all(|ch| c.read_raw(ch).ok() == Some(16384))
    })?;
    // raw × full scale / 32768, each channel with its own PGA range.
    for (ch, volts) in [(0, 2.048), (1, 0.128), (2, 3.072)] {
        let v = c.read(ch)?;
        assert!(
            (v - volts).abs() < 1e-12,
            "channel {ch}: {v} V, not {volts}"
        );
    }
    stub.set_word(0x48, 0x00, wire(-32768))?;
    wait("the negative full scale", || {
        (0..3).all(|ch| c.read_raw(ch).ok() == Some(-32768))
    })?;
    assert_eq!((c.read(0)?, c.read(1)?), (-4.096, -0.256));
    // The config word the chip was last given, as i2cget reads it (datasheet bits, MSB
    // first on the wire): OS | MUX | PGA | MODE single-shot | DR 860 | comparator off.
    // COMP_LAT (bit 2) set too: no word hwgw writes is the power-on value 0x8583.
    let configs = [
        wire(0xc3e7u16 as i16), // a0 (MUX 100), ±4.096 V (PGA 001)
        wire(0x8be7u16 as i16), // a0-a1 (MUX 000), ±0.256 V (PGA 101)
        wire(0xf1e7u16 as i16), // a3 (MUX 111), ±6.144 V (PGA 000)
    ];
    let config = stub.get_word(0x48, 0x01)?;
    assert!(configs.contains(&config), "config {config:#06x}");
    Ok(())
}

fn mcp4725_codes_as_i2c_stub_stores_them() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x60])?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"mcp4725\"\naddress = 0x60\npoll_ms = 2\nvref_v = 5.0\ninitial_v = 1.0",
    )?;
    let c = up.card.clone();
    wait("the DAC online", || c.counters().chips[0].online)?;
    // 1.0 V of 5.0 V: code 819 = 0x333, sent as "register" 0x03 (PD 00, D11..D8) with
    // data 0x33 (D7..D0).
    assert_eq!(c.read_back_raw(0)?, 819);
    assert_eq!(stub.get_byte(0x60, 0x03)?, 0x33);
    c.write(0, 3.3)?;
    assert_eq!(c.read_back_raw(0)?, 2703, "3.3 V × 4096 / 5 V");
    wait("code 0xa8f sent", || {
        stub.get_byte(0x60, 0x0a).ok() == Some(0x8f)
    })?;
    c.write_raw(0, 0x5c)?;
    wait("code 0x05c sent", || {
        stub.get_byte(0x60, 0x00).ok() == Some(0x5c)
    })?;
    assert!(c.write_raw(0, 4096).is_err(), "past 12 bits");
    let ao = c.devices().analog_out.unwrap();
    conformance::check_analog_out(&*ao).assert_complete();
    Ok(())
}

/// `angle` as the AS5600 sends RAW ANGLE (MSB first) read as an SMBus word.
fn angle_word(angle: i64) -> u16 {
    (angle.rem_euclid(4096) as u16).swap_bytes()
}

fn as5600_counts_turns_across_the_wrap() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x36])?;
    stub.set_byte(0x36, 0x0b, 0x20)?; // STATUS: magnet detected
    stub.set_word(0x36, 0x0c, angle_word(4000))?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"as5600\"\naddress = 0x36\npoll_ms = 2",
    )?;
    let c = up.card.clone();
    let enc = c.devices().encoders.remove(0).1;
    let at =
        |pos: i64, turn: i64| enc.position().ok() == Some(pos) && enc.turn().ok() == Some(turn);
    wait("the angle as the position", || at(4000, 0))?;
    stub.set_word(0x36, 0x0c, angle_word(100))?;
    wait("forwards across the wrap", || at(100, 1))?;
    stub.set_word(0x36, 0x0c, angle_word(3900))?;
    wait("back across it", || at(3900, 0))?;
    // Homed here.
    enc.set_position(0)?;
    // The magnet removed: the chip is failing, the encoder offline; back, and counted on
    // from where it was by the shortest way (3900 to 10: 206 counts on), the homing kept.
    stub.set_byte(0x36, 0x0b, 0x00)?;
    wait("offline without a magnet", || {
        matches!(enc.position(), Err(DeviceError::Offline))
    })?;
    let why = c.counters().chips[0].last_error.clone().unwrap_or_default();
    assert!(why.contains("no magnet"), "{why}");
    stub.set_word(0x36, 0x0c, angle_word(10))?;
    stub.set_byte(0x36, 0x0b, 0x20)?;
    wait("back, counted on", || at(206, 0))?;
    // The conformance kit, moving the magnet at most 1000 counts between readings.
    let angle = std::cell::Cell::new(10i64);
    let mut motion = |counts: i64| {
        let total =
            |e: &dyn device_interface::Encoder| e.turn().unwrap() * 4096 + e.position().unwrap();
        let target = total(&*enc) + counts;
        let mut left = counts;
        while left != 0 {
            let step = left.clamp(-1000, 1000);
            angle.set(angle.get() + step);
            stub.set_word(0x36, 0x0c, angle_word(angle.get())).unwrap();
            let want = target - left + step;
            wait_for("the encoder follows", PATIENCE, || total(&*enc) == want).unwrap();
            left -= step;
        }
    };
    conformance::check_encoder(&*enc, Some(&mut motion)).assert_complete();
    Ok(())
}

fn ina219_reads_shunt_bus_and_current_with_its_lsbs() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x40])?;
    // Big-endian registers, written as SMBus words: shunt 1000 counts, bus 3000 counts
    // (bits 15..3) with a conversion ready (CNVR, bit 1: the chip publishes nothing after
    // its set-up until a conversion finished), current 2000 counts.
    stub.set_word(0x40, 0x01, 1000u16.swap_bytes())?;
    stub.set_word(0x40, 0x02, (3000u16 << 3 | CNVR).swap_bytes())?;
    stub.set_word(0x40, 0x04, 2000u16.swap_bytes())?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"ina219\"\naddress = 0x40\npoll_ms = 2",
    )?;
    let c = up.card.clone();
    wait("the monitor online", || c.counters().chips[0].online)?;
    // The configuration and the calibration for 3.2 A over 0.1 Ω:
    // trunc(0.04096 / (3.2 / 32768 × 0.1)) = 4194 (0x1062, even: bit 0 is void), and the
    // current LSB the chip works with for it, 0.04096 / (4194 × 0.1) A.
    assert_eq!(stub.get_word(0x40, 0x00)?, 0x399fu16.swap_bytes());
    assert_eq!(stub.get_word(0x40, 0x05)?, 0x1062u16.swap_bytes());
    for (ch, want) in [(0, 0.01), (1, 12.0), (2, 2000.0 * 0.04096 / (4194.0 * 0.1))] {
        let got = c.read(ch)?;
        assert!(
            (got - want).abs() < 1e-12,
            "channel {ch}: {got}, not {want}"
        );
    }
    // A negative shunt voltage and current (reverse flow).
    stub.set_word(0x40, 0x01, (-400i16 as u16).swap_bytes())?;
    stub.set_word(0x40, 0x04, (-800i16 as u16).swap_bytes())?;
    wait("reverse flow", || {
        c.read_raw(0).ok() == Some(-400) && c.read_raw(2).ok() == Some(-800)
    })?;
    let ai = c.devices().analog_in.unwrap();
    let mut set_ai = |ch: u32, raw: i64| {
        let (reg, word) = match ch {
            0 => (0x01, raw as i16 as u16),
            1 => (0x02, (raw as u16) << 3),
            _ => (0x04, raw as i16 as u16),
        };
        stub.set_word(0x40, reg, word.swap_bytes()).unwrap();
        wait_for("the channel follows", PATIENCE, || {
            c.read_raw(ch).ok() == Some(raw)
        })
        .unwrap();
    };
    conformance::check_analog_in(&*ai, Some(&mut set_ai)).assert_complete();
    Ok(())
}

/// The INA219's bus voltage register: conversion ready.
const CNVR: u16 = 1 << 1;

fn ina219_found_reset_is_set_up_again_and_its_lost_current_never_published() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x40])?;
    // Big-endian registers, written as the chip shows them.
    let ina = |reg: u8, word: u16| stub.set_word(0x40, reg, word.swap_bytes());
    ina(0x01, 1000)?;
    ina(0x04, 2000)?;
    ina(0x02, 3000 << 3 | CNVR)?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"ina219\"\naddress = 0x40\npoll_ms = 2",
    )?;
    let c = up.card.clone();
    let chip = || c.counters().chips[0].clone();
    wait("the current read", || c.read_raw(2).ok() == Some(2000))?;
    assert_eq!(stub.get_word(0x40, 0x05)?, 0x1062u16.swap_bytes());
    // A brown-out: the registers at their power-on values. The bus voltage register first
    // (no conversion ready), then calibration 0 — from here on a real chip's current and
    // power read 0 — then the rest, so that no poll reads a 0 current beside hwgw's
    // calibration (i2c-stub's registers change one i2cset at a time).
    ina(0x02, 0)?;
    ina(0x00, 0x399f)?;
    ina(0x05, 0)?;
    ina(0x04, 0)?;
    ina(0x03, 0)?;
    ina(0x01, 0)?;
    wait("the reset noticed", || chip().resets == 1)?;
    let found = chip().last_reset.unwrap_or_default();
    assert_eq!(found, "calibration reads 0x0000, not 0x1062");
    // Set up again, as i2c-tools reads it.
    wait("the calibration written again", || {
        stub.get_word(0x40, 0x05).ok() == Some(0x1062u16.swap_bytes())
    })?;
    assert_eq!(stub.get_word(0x40, 0x00)?, 0x399fu16.swap_bytes());
    // Polled on since (or offline: i2c-stub does not convert, so no conversion finishes
    // after the set-up and the polls fail past their deadline), and the 0 current the
    // stub holds was never published: it was read with the lost calibration, or before a
    // conversion with the new one.
    let polls = chip().polls;
    wait("polled since", || {
        let now = chip();
        now.polls >= polls + 3 || !now.online
    })?;
    match c.read_raw(2) {
        Ok(raw) => assert_eq!(raw, 2000, "the last current read right"),
        Err(e) => assert!(matches!(e, DeviceError::Offline), "{e}"),
    }
    // The chip converts with the calibration again: new values, bus voltage (with CNVR)
    // last.
    ina(0x01, 750)?;
    ina(0x04, 1500)?;
    ina(0x02, 2500 << 3 | CNVR)?;
    wait("the values back", || {
        (0..3).map(|ch| c.read_raw(ch).ok()).collect::<Vec<_>>()
            == [Some(750), Some(2500), Some(1500)]
    })?;
    let now = chip();
    assert!(now.online, "{now:?}");
    assert_eq!(now.resets, 1, "{now:?}");
    Ok(())
}

/// The ADS1115 sections of the reset and stuck tests: one channel, its config word
/// `ADS_CONFIG` (a0, ±4.096 V, single-shot, 860/s, comparator off, COMP_LAT).
const ADS_ONE: &str = r#"
[[chip]]
model = "ads1115"
address = 0x48
poll_ms = 2
channel = [{ input = "a0", range_v = 4.096 }]
"#;
const ADS_CONFIG: u16 = 0xc3e7;
/// OS: written 1 starts a conversion; read 0, one is under way.
const OS: u16 = 0x8000;

fn ads1115_found_reset_is_set_up_again() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x48])?;
    stub.set_word(0x48, 0x00, wire(16384))?;
    let up = up(&stub, ADS_ONE)?;
    let c = up.card.clone();
    let chip = || c.counters().chips[0].clone();
    wait("converted", || c.read_raw(0).ok() == Some(16384))?;
    assert_eq!(stub.get_word(0x48, 0x01)?, ADS_CONFIG.swap_bytes());
    // A brown-out: Config at its power-on value 0x8583. hwgw writes Config to start each
    // conversion, so a value written just before that is overwritten unseen (as a reset
    // just before it would be undone): written again until a poll finds it.
    let power_on = 0x8583u16.swap_bytes();
    wait("the reset noticed", || {
        if chip().resets > 0 {
            return true;
        }
        if stub.get_word(0x48, 0x01).ok() != Some(power_on) {
            stub.set_word(0x48, 0x01, power_on).unwrap();
        }
        false
    })?;
    let found = chip().last_reset.unwrap_or_default();
    assert_eq!(found, "config reads 0x8583, not 0xc3e7");
    wait("its config written again", || {
        stub.get_word(0x48, 0x01).ok() == Some(ADS_CONFIG.swap_bytes())
    })?;
    // Converting as before: a new result read.
    stub.set_word(0x48, 0x00, wire(-1234))?;
    wait("the next result", || c.read_raw(0).ok() == Some(-1234))?;
    assert!(chip().online);
    assert_eq!(c.read(0)?, -1234.0 * 4.096 / 32768.0);
    Ok(())
}

fn a_stuck_ads1115_goes_offline_and_back_when_it_converts() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x48])?;
    stub.set_word(0x48, 0x00, wire(16384))?;
    let up = up(&stub, ADS_ONE)?;
    let c = up.card.clone();
    let chip = || c.counters().chips[0].clone();
    wait("converted", || c.read_raw(0).ok() == Some(16384))?;
    // Stuck: OS stays 0 (a conversion under way) with hwgw's config. Until a poll sees it,
    // hwgw's next conversion start may overwrite it: written again until it holds — from
    // then on hwgw does not write Config (OS written during a conversion does nothing).
    let stuck = (ADS_CONFIG & !OS).swap_bytes();
    wait("offline, not converting", || {
        let now = chip();
        if !now.online && now.last_error.is_some_and(|e| e.contains("not converting")) {
            return true;
        }
        if stub.get_word(0x48, 0x01).ok() != Some(stuck) {
            stub.set_word(0x48, 0x01, stuck).unwrap();
        }
        false
    })?;
    let why = chip().last_error.unwrap_or_default();
    assert!(
        why.starts_with("channel 0's conversion not done within"),
        "{why}"
    );
    assert!(matches!(c.read_raw(0), Err(DeviceError::Offline)));
    // Probed with a backoff, it stays offline: each probe finds the conversion under way,
    // waits on it and counts it overdue.
    let errors = chip().errors;
    wait("probed three times more", || chip().errors >= errors + 3)?;
    let now = chip();
    assert!(!now.online, "{now:?}");
    assert_eq!(now.went_offline, 1, "{now:?}");
    assert_eq!(stub.get_word(0x48, 0x01)?, stuck, "never started again");
    // It converts again: the result, and online.
    stub.set_word(0x48, 0x00, wire(8192))?;
    stub.set_word(0x48, 0x01, ADS_CONFIG.swap_bytes())?;
    wait("online with the new result", || {
        chip().online && c.read_raw(0).ok() == Some(8192)
    })?;
    Ok(())
}

fn pca9685_sets_its_prescale_and_duty_registers() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x41])?;
    // As after power-on: ALLCALL, asleep, prescale 30 (200 Hz).
    stub.set_byte(0x41, 0x00, 0x11)?;
    stub.set_byte(0x41, 0xfe, 30)?;
    let up = up(
        &stub,
        "[[chip]]\nmodel = \"pca9685\"\naddress = 0x41\npoll_ms = 2\nfrequency_hz = 50\nchannels = [3, 0]",
    )?;
    let c = up.card.clone();
    wait("the PWM online", || c.counters().chips[0].online)?;
    // 50 Hz: round(25 MHz / (4096 × 50)) − 1 = 121; awake with auto-increment, ALLCALL
    // kept.
    assert_eq!(stub.get_byte(0x41, 0xfe)?, 121);
    assert_eq!(stub.get_byte(0x41, 0x00)?, 0x21);
    // Both start full off: LEDn_OFF bit 12.
    assert_eq!(stub.get_word(0x41, 0x06 + 4 * 3 + 2)?, 0x1000);
    assert_eq!(stub.get_word(0x41, 0x06 + 2)?, 0x1000);
    c.write(0, 0.25)?;
    c.write(1, 1.0)?;
    wait("output 3 at 25 %, output 0 full on", || {
        stub.get_word(0x41, 0x14).ok() == Some(1024)
            && stub.get_word(0x41, 0x12).ok() == Some(0)
            && stub.get_word(0x41, 0x06).ok() == Some(0x1000)
            && stub.get_word(0x41, 0x08).ok() == Some(0)
    })?;
    let ao = c.devices().analog_out.unwrap();
    conformance::check_analog_out(&*ao).assert_complete();
    Ok(())
}

fn writes_go_out_at_once_and_chips_found_reset_are_set_up_again() -> Result<(), Failed> {
    let stub = I2cStub::load(&[0x20, 0x21, 0x41, 0x60])?;
    let up = up(
        &stub,
        r#"
[[chip]]
model = "mcp23017"
address = 0x20
poll_ms = 60000
outputs = [0]
[[chip]]
model = "mcp23017"
address = 0x21
poll_ms = 10
outputs = [0]
initial_on = [0]
[[chip]]
model = "pca9685"
address = 0x41
poll_ms = 10
frequency_hz = 50
channels = [0]
[[chip]]
model = "mcp4725"
address = 0x60
poll_ms = 10
vref_v = 5.0
"#,
    )?;
    let c = up.card.clone();
    wait("all online", || c.counters().online == "4/4")?;
    let resets = |i: usize| c.counters().chips[i].resets;
    // A chip polled once a minute: a write is sent when it is made, not at the next poll
    // (this wait gives up long before that).
    c.set_bit(0, true)?;
    wait("OLAT of 0x20 at 1", || {
        stub.get_word(0x20, 0x14).ok() == Some(1)
    })?;
    c.write(0, 0.5)?;
    c.write_raw(1, 0xa8f)?;
    wait("the duty and the code sent", || {
        stub.get_word(0x41, 0x08).ok() == Some(2048) && stub.get_byte(0x60, 0x0a).ok() == Some(0x8f)
    })?;
    // Each loses its set-up as a power loss would leave it, what the checks read last
    // (IODIR; MODE1), so whichever check sees a loss sets up everything lost before it.
    stub.set_word(0x21, 0x14, 0x0000)?;
    stub.set_word(0x21, 0x00, 0xffff)?;
    stub.set_word(0x41, 0x08, 0x1000)?;
    stub.set_byte(0x41, 0xfe, 30)?;
    stub.set_byte(0x41, 0x00, 0x11)?;
    stub.set_byte(0x60, 0x0a, 0x00)?;
    wait("the expander set up again", || {
        stub.get_word(0x21, 0x00).ok() == Some(0xfffe) && stub.get_word(0x21, 0x14).ok() == Some(1)
    })?;
    assert_eq!(resets(1), 1);
    wait("the PWM set up again", || {
        stub.get_byte(0x41, 0x00).ok() == Some(0x21)
            && stub.get_byte(0x41, 0xfe).ok() == Some(121)
            && stub.get_word(0x41, 0x08).ok() == Some(2048)
    })?;
    assert!(resets(2) >= 1);
    wait("the DAC's code sent again", || {
        stub.get_byte(0x60, 0x0a).ok() == Some(0x8f)
    })?;
    assert_eq!(resets(3), 0, "the DAC's check only sends");
    assert_eq!(resets(0), 0);
    assert!(
        c.counters()
            .chips
            .iter()
            .all(|chip| chip.online && chip.errors == 0),
        "{:?}",
        c.counters()
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::i2c_stub(),
        vec![
            Trial::test(
                "mcp23017_registers_as_i2c_tools_sees_them",
                mcp23017_registers_as_i2c_tools_sees_them,
            ),
            Trial::test(
                "a_chip_that_does_not_answer_is_offline_and_others_keep_polling",
                a_chip_that_does_not_answer_is_offline_and_others_keep_polling,
            ),
            Trial::test(
                "ads1115_converts_with_each_range_and_sign",
                ads1115_converts_with_each_range_and_sign,
            ),
            Trial::test(
                "mcp4725_codes_as_i2c_stub_stores_them",
                mcp4725_codes_as_i2c_stub_stores_them,
            ),
            Trial::test(
                "as5600_counts_turns_across_the_wrap",
                as5600_counts_turns_across_the_wrap,
            ),
            Trial::test(
                "ina219_reads_shunt_bus_and_current_with_its_lsbs",
                ina219_reads_shunt_bus_and_current_with_its_lsbs,
            ),
            Trial::test(
                "ina219_found_reset_is_set_up_again_and_its_lost_current_never_published",
                ina219_found_reset_is_set_up_again_and_its_lost_current_never_published,
            ),
            Trial::test(
                "ads1115_found_reset_is_set_up_again",
                ads1115_found_reset_is_set_up_again,
            ),
            Trial::test(
                "a_stuck_ads1115_goes_offline_and_back_when_it_converts",
                a_stuck_ads1115_goes_offline_and_back_when_it_converts,
            ),
            Trial::test(
                "pca9685_sets_its_prescale_and_duty_registers",
                pca9685_sets_its_prescale_and_duty_registers,
            ),
            Trial::test(
                "writes_go_out_at_once_and_chips_found_reset_are_set_up_again",
                writes_go_out_at_once_and_chips_found_reset_are_set_up_again,
            ),
            Trial::test("the_conformance_kit_passes", the_conformance_kit_passes),
        ],
    )
}
