//! An example of a user's own bus driver, registered beside hwgw's built-in ones.
//!
//! `loopback` is a card whose inputs read, one bus cycle later, what its outputs were set
//! to: analog output n drives analog input n, digital output n drives digital input n. Its
//! bus side is a periodic component (named after the card) that copies the outputs to the
//! inputs each cycle, as a real card's bus component would exchange them with hardware.
//!
//! The whole driver is this file: a section type (`[card.loopback]`), the devices (the
//! five interfaces' contract: non-blocking, allocation-free, errors as values), a
//! [`Card`] for the gateway and its bus side (a [`BusSide`] handed over by value from
//! [`build`]), and one registration line in [`types`]. The binary in
//! `src/main.rs` is the whole `hwgw` command line with the driver added:
//!
//! ```text
//! cargo run -p hwgw-example-driver -- run examples/custom-driver/loopback.toml
//! cargo run -p hwgw-example-driver -- set loop.ao setpoint 2500
//! cargo run -p hwgw-example-driver -- get loop.ai feedback
//! ```

use device_interface::bits::{BitImage, BitSpan, DigitalInputImage, DigitalOutputImage, Written};
use device_interface::time::Clock;
use device_interface::{
    AnalogIn, AnalogOut, CardDevices, Device, DeviceError, Health, RawRange, Scale, Status, Unit,
};
use driver_api::{BuiltCard, BusSide, Card, CardContext, CardError, CardStatus};
use hwgw::types::Types;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

/// Most channels of each kind a loopback card may have (a bound on what a
/// deployment can make it allocate).
pub const MAX_CHANNELS: u32 = 1024;

/// The `[card.loopback]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoopbackConfig {
    /// Analog channels (each an output and the input it drives; default 4).
    #[serde(default = "four")]
    pub analog: u32,
    /// Digital channels (default 8).
    #[serde(default = "eight")]
    pub digital: u32,
    /// Lowest analog value (default -10).
    #[serde(default = "minus_ten")]
    pub lowest: f64,
    /// Highest analog value (default 10).
    #[serde(default = "ten")]
    pub highest: f64,
    /// Unit of the analog values (default V).
    #[serde(default = "volt")]
    pub unit: String,
    /// Resolution of the analog channels in bits, 2 to 32 (default 16).
    #[serde(default = "sixteen")]
    pub bits: u32,
}

fn four() -> u32 {
    4
}
fn eight() -> u32 {
    8
}
fn sixteen() -> u32 {
    16
}
fn minus_ten() -> f64 {
    -10.0
}
fn ten() -> f64 {
    10.0
}
fn volt() -> String {
    "V".into()
}

/// The loopback card's devices.
pub struct Loopback {
    scale: Scale,
    outputs: Vec<AtomicI64>,
    inputs: Vec<AtomicI64>,
    digital_out: BitImage,
    digital_in: BitImage,
    cycles: AtomicU64,
    clock: Arc<dyn Clock>,
}

/// The card's counters, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct LoopbackCounters {
    /// Bus cycles run.
    pub cycles: u64,
}

impl Loopback {
    /// A card as `config` says; errors name the key.
    pub fn new(config: &LoopbackConfig, clock: Arc<dyn Clock>) -> Result<Arc<Loopback>, CardError> {
        for (key, n) in [("analog", config.analog), ("digital", config.digital)] {
            if n > MAX_CHANNELS {
                return Err(CardError::at(
                    key,
                    format!("{n} channels: at most {MAX_CHANNELS}"),
                ));
            }
        }
        if !(2..=32).contains(&config.bits) {
            return Err(CardError::at(
                "bits",
                format!("{}: expected 2 to 32", config.bits),
            ));
        }
        let raw = RawRange::unsigned_bits(config.bits).map_err(|e| CardError::at("bits", e))?;
        let unit = Unit::new(&config.unit).map_err(|e| CardError::at("unit", e))?;
        let scale = Scale::linear(raw, config.lowest, config.highest, unit)
            .map_err(|e| CardError::at("lowest", e))?;
        // Outputs start at the value nearest 0 (or the range's low end).
        let start = scale.to_raw_saturating(0.0);
        let channels = |n: u32| (0..n).map(|_| AtomicI64::new(start)).collect();
        Ok(Arc::new(Loopback {
            scale,
            outputs: channels(config.analog),
            inputs: channels(config.analog),
            digital_out: BitImage::new(config.digital),
            digital_in: BitImage::new(config.digital),
            cycles: AtomicU64::new(0),
            clock,
        }))
    }

    /// One bus cycle: every input takes its output's value.
    pub fn cycle(&self) {
        for (i, o) in self.inputs.iter().zip(&self.outputs) {
            i.store(o.load(Ordering::Acquire), Ordering::Release);
        }
        for b in 0..self.digital_out.len() {
            let _ = self
                .digital_in
                .set(b, self.digital_out.get(b).unwrap_or(false));
        }
        self.cycles.fetch_add(1, Ordering::Relaxed);
    }

    fn channel(&self, list: &[AtomicI64], channel: u32) -> Result<i64, DeviceError> {
        list.get(channel as usize)
            .map(|v| v.load(Ordering::Acquire))
            .ok_or(DeviceError::ChannelOutOfRange {
                channel,
                count: list.len() as u32,
            })
    }

    /// The devices, for the registry (only the interfaces it has channels for).
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        let (analog, digital) = (!self.outputs.is_empty(), !self.digital_out.is_empty());
        CardDevices {
            analog_in: analog.then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: analog.then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: digital.then(|| self.clone() as Arc<dyn device_interface::DigitalIn>),
            digital_out: digital.then(|| self.clone() as Arc<dyn device_interface::DigitalOut>),
            drives: Vec::new(),
            encoders: Vec::new(),
        }
    }
}

impl Device for Loopback {
    fn health(&self) -> Health {
        Health {
            status: Status::Online,
            last_good: Some(self.clock.now()),
            checked_at: self.clock.now(),
            last_error: None,
        }
    }
}

impl AnalogIn for Loopback {
    fn channel_count(&self) -> u32 {
        self.inputs.len() as u32
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.channel(&self.inputs, channel).map(|_| self.scale)
    }
    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.channel(&self.inputs, channel)
    }
}

impl AnalogOut for Loopback {
    fn channel_count(&self) -> u32 {
        self.outputs.len() as u32
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.channel(&self.outputs, channel).map(|_| self.scale)
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.channel(&self.outputs, channel)?;
        self.scale.check_raw(channel, raw)?;
        self.outputs[channel as usize].store(raw, Ordering::Release);
        Ok(())
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.channel(&self.outputs, channel)
    }
}

impl DigitalInputImage for Loopback {
    fn inputs(&self) -> &BitImage {
        &self.digital_in
    }
    fn check_inputs(&self, _: BitSpan) -> Result<(), DeviceError> {
        Ok(())
    }
}

impl DigitalOutputImage for Loopback {
    fn outputs(&self) -> &BitImage {
        &self.digital_out
    }
    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        Ok(())
    }
    fn outputs_written(&self, _: Written) {}
}

/// A loopback card of a deployment.
struct LoopbackCard {
    card: Arc<Loopback>,
    period: Duration,
}

impl Card for LoopbackCard {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn read_back(&self) -> driver_api::ReadBack {
        // The loopback's outputs are its whole state.
        driver_api::ReadBack::Device
    }

    fn summary(&self) -> String {
        format!(
            "{} analog and {} digital channels looped back every {:?}",
            self.card.outputs.len(),
            self.card.digital_out.len(),
            self.period
        )
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(
            "memory",
            &LoopbackCounters {
                cycles: self.card.cycles.load(Ordering::Relaxed),
            },
        )
    }
}

/// The driver: builds a loopback card from its section, and its bus side: a component
/// named after the card that copies the outputs to the inputs every period, on the card's
/// thread.
pub fn build(config: &LoopbackConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let card = Loopback::new(config, ctx.clock())?;
    let cycled = card.clone();
    let bus = BusSide::periodic(ctx.period(), move || cycled.cycle());
    let period = ctx.period();
    Ok(BuiltCard::new(LoopbackCard { card, period }, bus))
}

/// hwgw's built-in component types and drivers, plus `loopback`.
pub fn types() -> Types {
    let mut t = Types::builtin();
    t.drivers.register("loopback", build);
    t
}
