//! A poll cycle of a bus of six chips, beside a bare i2cdev loop making the same transfers
//! in the same guest run.
//!
//! `cargo bench -p driver-i2c --bench i2c` boots the kernel rig and runs this inside, on
//! i2c-stub with an MCP23017, an AS5600, an INA219, a PCA9685, an ADS1115 and an MCP4725.
//! hwgw's side is the card's bus side stepped with every chip due each time (what the
//! bus thread does each cycle: the models, the images, the counters, and every 500th
//! cycle the chips' set-up checks); the reference makes the same SMBus transfers to the
//! same registers through `i2cdev` with nothing around them (no checks). Both count their transfers; the figures are transfers per second and the cycle
//! time, and their ratio.
#![allow(clippy::unwrap_used, reason = "benchmark code")]

use device_interface::time::{MonotonicClock, Timestamp};
use driver_i2c::bus::I2cBus;
use driver_i2c::config::I2cConfig;
use driver_i2c::smbus::{LinuxChip, Smbus, Transfer};
use i2cdev::core::I2CDevice;
use i2cdev::linux::LinuxI2CDevice;
use kernel_rig::{Failed, Trial};
use std::hint::black_box;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use testkit::I2cStub;
use testkit::bench::{mean, rate as run};

const CHIPS: &str = r#"
[[chip]]
model = "mcp23017"
address = 0x20
poll_ms = 1
inputs = [8, 9]
outputs = [0]
[[chip]]
model = "as5600"
address = 0x36
poll_ms = 1
[[chip]]
model = "ina219"
address = 0x40
poll_ms = 1
[[chip]]
model = "pca9685"
address = 0x41
poll_ms = 1
frequency_hz = 1000
channels = [0]
[[chip]]
model = "ads1115"
address = 0x48
poll_ms = 1
channel = [{ input = "a0", range_v = 4.096 }]
[[chip]]
model = "mcp4725"
address = 0x60
poll_ms = 1
vref_v = 5.0
"#;

/// Counts the transfers it passes on.
struct Counting(LinuxChip, Arc<AtomicU64>);

impl Counting {
    fn count<T>(&self, r: Result<T, Transfer>) -> Result<T, Transfer> {
        self.1.fetch_add(1, Ordering::Relaxed);
        r
    }
}

impl Smbus for Counting {
    fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer> {
        let r = self.0.read_byte(reg);
        self.count(r)
    }
    fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer> {
        let r = self.0.write_byte(reg, value);
        self.count(r)
    }
    fn read_word(&mut self, reg: u8) -> Result<u16, Transfer> {
        let r = self.0.read_word(reg);
        self.count(r)
    }
    fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer> {
        let r = self.0.write_word(reg, value);
        self.count(r)
    }
}

/// Transfers a bare cycle makes.
const BARE: u64 = 10;

fn bus_bench(quick: bool) -> Result<u64, Failed> {
    let cycles = if quick { 100 } else { 20_000 };
    let stub = I2cStub::load(&[0x20, 0x36, 0x40, 0x41, 0x48, 0x60])?;
    stub.set_byte(0x36, 0x0b, 0x20)?; // the AS5600 sees a magnet
    stub.set_word(0x40, 0x02, 0x0200)?; // the INA219 has a conversion ready (CNVR)
    stub.set_word(0x48, 0x00, 0x0040)?; // the ADS1115's result is not 0 (no second look)
    let config: I2cConfig = toml::from_str(&format!(
        "bus = {:?}\n{CHIPS}",
        stub.path().display().to_string()
    ))?;
    let built = driver_i2c::plugin::card(&config, Arc::new(MonotonicClock))
        .map_err(|e| Failed::from(e.message))?;
    let counted = Arc::new(AtomicU64::new(0));
    let path = stub.path();
    let opener_count = counted.clone();
    let card = built.card.clone();
    let mut bus = I2cBus::with_opener(
        built.card,
        built.models,
        Box::new(move |address| {
            let chip = LinuxChip::open(&path, address)?;
            Ok(Box::new(Counting(chip, opener_count.clone())) as Box<dyn Smbus>)
        }),
    );
    // Every chip due at each step: one poll period (1 ms) later each time, from now on, so
    // each chip's set-up check comes every 500th cycle, as on the bus thread.
    let mut t = device_interface::time::Clock::now(&MonotonicClock).as_nanos();
    let mut step = || {
        t += 1_000_000;
        bus.step(Timestamp::from_nanos(t));
    };
    // Set up, then the first samples (the INA219 and the ADS1115 go online with theirs).
    step();
    step();
    let online = card.counters().online;
    if online != "6/6" {
        return Err(format!("chips online: {online}: {:?}", card.counters().chips).into());
    }
    let mut devices: Vec<LinuxI2CDevice> = [0x20u16, 0x36, 0x40, 0x48]
        .iter()
        .map(|a| LinuxI2CDevice::new(stub.path(), *a).unwrap())
        .collect();
    // The same transfers as one hwgw cycle with no output changed: MCP23017 GPIO; AS5600
    // STATUS, RAW ANGLE; INA219 bus, shunt, current, calibration; ADS1115 config,
    // conversion, config.
    let mut bare = || -> u64 {
        let [mcp, angle, ina, adc] = &mut devices[..] else {
            return 0;
        };
        black_box(mcp.smbus_read_word_data(0x12).unwrap());
        black_box(angle.smbus_read_byte_data(0x0b).unwrap());
        black_box(angle.smbus_read_word_data(0x0c).unwrap());
        for reg in [0x02, 0x01, 0x04, 0x05] {
            black_box(ina.smbus_read_word_data(reg).unwrap());
        }
        black_box(adc.smbus_read_word_data(0x01).unwrap());
        black_box(adc.smbus_read_word_data(0x00).unwrap());
        adc.smbus_write_word_data(0x01, 0xe7c3).unwrap();
        BARE
    };
    // Interleaved rounds so a noisy moment hits both alike.
    let (mut ours, mut theirs) = (Vec::new(), Vec::new());
    for _ in 0..10 {
        let before = counted.load(Ordering::Relaxed);
        let (_, us) = run(cycles / 10, || {
            step();
            0
        });
        let per_cycle = (counted.load(Ordering::Relaxed) - before) as f64 / f64::from(cycles / 10);
        ours.push((per_cycle * 1e6 / us, us, per_cycle));
        theirs.push(run(cycles / 10, &mut bare));
    }
    let our_tps = mean(ours.iter().map(|x| x.0));
    let our_us = mean(ours.iter().map(|x| x.1));
    let per_cycle = mean(ours.iter().map(|x| x.2));
    let bare_tps = mean(theirs.iter().map(|x| x.0));
    let bare_us = mean(theirs.iter().map(|x| x.1));
    println!("a poll cycle of six chips on i2c-stub, {cycles} cycles each:");
    println!(
        "  hwgw bus side   {our_tps:9.0} transfers/s   {our_us:7.1} µs a cycle ({per_cycle:.1} transfers)"
    );
    println!(
        "  bare i2cdev     {bare_tps:9.0} transfers/s   {bare_us:7.1} µs a cycle ({BARE} transfers)"
    );
    println!(
        "  hwgw / bare: transfers/s {:.2}, cycle time {:.2}",
        our_tps / bare_tps,
        our_us / bare_us
    );
    let errors: u64 = card.counters().chips.iter().map(|c| c.errors).sum();
    if errors != 0 {
        return Err(format!("{errors} failed transfers: {:?}", card.counters().chips).into());
    }
    Ok((our_us * 1000.0) as u64)
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &testkit::rig::i2c_stub(),
        vec![Trial::bench("poll_cycle", |test_mode| {
            let ns = bus_bench(test_mode)?;
            Ok((!test_mode).then_some(kernel_rig::Measurement {
                avg: ns,
                variance: 0,
            }))
        })],
    )
}
