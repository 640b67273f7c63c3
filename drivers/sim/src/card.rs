//! The simulated card: device images, the simulation step, faults and test hooks.

use crate::config::{SimConfig, Waveform};
use crate::record::{OutputEvent, OutputRecord, OutputWrite};
use arc_swap::ArcSwapOption;
use device_interface::bits::{BitImage, BitSpan};
use device_interface::encoder::EncoderCounter;
use device_interface::text::Number;
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, CardDevices, Device, DeviceError, DigitalIn, DigitalOut, Encoder, Health,
    Registry, RegistryError, Scale, ScaleError, Status,
};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Why a [`SimConfig`] was refused; each names the key path of the problem.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SimConfigError {
    /// A range, raw range or unit that does not make a scale.
    #[error("{path}: {source}")]
    Scale {
        /// Key path, e.g. `analog_in[1].range`.
        path: String,
        /// What is wrong with it.
        #[source]
        source: ScaleError,
    },
    /// A loopback or velocity source naming an analog output the card does not have.
    #[error("{path}: analog output {channel} does not exist (the card has {count} analog outputs)")]
    NoSuchAnalogOut {
        /// Key path.
        path: String,
        /// The channel named.
        channel: u32,
        /// How many analog outputs the card has.
        count: u32,
    },
    /// A value outside what the key accepts.
    #[error("{path}: {problem}")]
    Invalid {
        /// Key path.
        path: String,
        /// What was expected.
        problem: String,
    },
}

impl SimConfigError {
    /// The key path under the section the error is about, and what is wrong with it.
    pub fn at(&self) -> (&str, String) {
        match self {
            SimConfigError::Scale { path, source } => (path, source.to_string()),
            SimConfigError::NoSuchAnalogOut {
                path,
                channel,
                count,
            } => (
                path,
                format!(
                    "analog output {channel} does not exist (the card has {count} analog outputs)"
                ),
            ),
            SimConfigError::Invalid { path, problem } => (path, problem.clone()),
        }
    }
}

/// A fault to simulate, set with [`SimCard::set_fault`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SimFault {
    /// Healthy: steps refresh the inputs.
    None,
    /// Inputs stop refreshing and read as [`DeviceError::Stale`]; outputs still work.
    Stale,
    /// The card is gone: inputs and outputs fail with [`DeviceError::Offline`].
    Offline,
    /// The bus fails: inputs and outputs fail with [`DeviceError::Bus`] carrying this text.
    Bus(String),
}

const FAULT_NONE: u8 = 0;
const FAULT_STALE: u8 = 1;
const FAULT_OFFLINE: u8 = 2;
const FAULT_BUS: u8 = 3;

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct SimulatedBusError(String);

struct AnalogInChannel {
    scale: Scale,
    waveform: Waveform,
    raw: AtomicI64,
    /// Set by a test hook: the step leaves the value alone.
    held: AtomicBool,
}

struct AnalogOutChannel {
    scale: Scale,
    raw: AtomicI64,
}

struct SimEncoderState {
    counter: EncoderCounter,
    /// Every count moved since the card was built (what position switches see).
    travel: AtomicI64,
    velocity_from: Option<u32>,
    counts_per_unit: f64,
}

struct StepState {
    last_step: Timestamp,
    /// Fractions of a count each encoder has moved but not yet counted.
    encoder_fraction: Vec<f64>,
}

/// A simulated IO card: analog and digital inputs and outputs and encoders, with waveforms,
/// loopbacks, injectable faults and a record of output writes.
///
/// Its device methods keep the real-time contract (atomics only); [`step`](Self::step) is
/// its bus cycle, run by the card's activity (or by hand in tests): it samples the
/// waveforms, copies loopbacks and moves the encoders, at the card clock's time.
pub struct SimCard {
    clock: Arc<dyn Clock>,
    epoch: Timestamp,
    seed: u64,
    ai: Box<[AnalogInChannel]>,
    ao: Box<[AnalogOutChannel]>,
    di: BitImage,
    di_held: BitImage,
    dout: BitImage,
    /// Digital inputs driven from outputs at each step.
    di_looped: BitImage,
    encoders: Box<[SimEncoderState]>,
    switches: crate::switch::Switches,
    fault: AtomicU8,
    bus_error: ArcSwapOption<DeviceError>,
    /// Time of the last good sample in ns plus one; 0 means never.
    last_good: AtomicU64,
    step_state: Mutex<StepState>,
    record: Option<OutputRecord>,
}

/// The most channels (or bits, or encoders) of each kind a simulated card has, and the
/// longest output record: bounds on what a section can make it allocate.
pub const MAX_CHANNELS: u32 = 65_536;
/// See [`MAX_CHANNELS`].
pub const MAX_RECORD: usize = 1 << 20;

/// Refuses a section that would make the card allocate without bound.
fn check_sizes(config: &SimConfig) -> Result<(), SimConfigError> {
    let too_many = |path: String, n: u64| {
        (n > u64::from(MAX_CHANNELS)).then(|| SimConfigError::Invalid {
            path,
            problem: format!("{n}: at most {MAX_CHANNELS}"),
        })
    };
    let groups = |g: &mut dyn Iterator<Item = u32>| g.map(u64::from).sum::<u64>();
    let checks = [
        too_many(
            "analog_in".into(),
            groups(&mut config.analog_in.iter().map(|g| g.count)),
        ),
        too_many(
            "analog_out".into(),
            groups(&mut config.analog_out.iter().map(|g| g.count)),
        ),
        too_many("digital_inputs".into(), u64::from(config.digital_inputs)),
        too_many("digital_outputs".into(), u64::from(config.digital_outputs)),
        too_many("encoder".into(), config.encoder.len() as u64),
    ];
    if let Some(e) = checks.into_iter().flatten().next() {
        return Err(e);
    }
    if config.record_capacity > MAX_RECORD {
        return Err(SimConfigError::Invalid {
            path: "record_capacity".into(),
            problem: format!("{}: at most {MAX_RECORD}", config.record_capacity),
        });
    }
    Ok(())
}

impl SimCard {
    /// Builds a card from `config`, with its time from `clock`, and takes its first sample.
    pub fn new(config: &SimConfig, clock: Arc<dyn Clock>) -> Result<Arc<SimCard>, SimConfigError> {
        check_sizes(config)?;
        let mut ao = Vec::new();
        for (g, group) in config.analog_out.iter().enumerate() {
            let path = format!("analog_out[{g}]");
            let scale = group_scale(&path, &group.range, group.raw)?;
            let raw = match group.initial {
                None => scale.to_raw_saturating(0.0),
                Some(v) => scale.to_raw(v).ok_or_else(|| SimConfigError::Invalid {
                    path: format!("{path}.initial"),
                    problem: format!("{} is outside the range {}", Number(v), scale.range()),
                })?,
            };
            for _ in 0..group.count {
                ao.push(AnalogOutChannel {
                    scale,
                    raw: AtomicI64::new(raw),
                });
            }
        }
        let ao_count = ao.len() as u32;
        let check_ao = |path: String, channel: u32| {
            if channel < ao_count {
                Ok(())
            } else {
                Err(SimConfigError::NoSuchAnalogOut {
                    path,
                    channel,
                    count: ao_count,
                })
            }
        };

        let mut ai = Vec::new();
        for (g, group) in config.analog_in.iter().enumerate() {
            let path = format!("analog_in[{g}]");
            let scale = group_scale(&path, &group.range, group.raw)?;
            check_waveform(&format!("{path}.waveform"), &group.waveform, &check_ao)?;
            for _ in 0..group.count {
                ai.push(AnalogInChannel {
                    scale,
                    waveform: group.waveform.clone(),
                    raw: AtomicI64::new(scale.to_raw_saturating(0.0)),
                    held: AtomicBool::new(false),
                });
            }
        }

        let mut encoders = Vec::new();
        for (i, e) in config.encoder.iter().enumerate() {
            let path = format!("encoder[{i}]");
            let counter = EncoderCounter::new(e.resolution, e.upcounting).map_err(|_| {
                SimConfigError::Invalid {
                    path: format!("{path}.resolution"),
                    problem: format!(
                        "{} is not a resolution: expected a non-zero count per turn",
                        e.resolution
                    ),
                }
            })?;
            if let Some(ch) = e.velocity_from {
                check_ao(format!("{path}.velocity_from"), ch)?;
            }
            check_speed(&path, e, &ao)?;
            encoders.push(SimEncoderState {
                counter,
                travel: AtomicI64::new(0),
                velocity_from: e.velocity_from,
                counts_per_unit: e.counts_per_unit,
            });
        }

        let di_looped = BitImage::new(config.digital_inputs);
        if config.digital_loopback {
            for b in 0..config.digital_inputs.min(config.digital_outputs) {
                di_looped
                    .set(b, true)
                    .map_err(|e| SimConfigError::Invalid {
                        path: "digital_loopback".into(),
                        problem: e.to_string(),
                    })?;
            }
        }

        let switches = crate::switch::Switches::new(
            &config.switch,
            config.digital_inputs,
            &di_looped,
            encoders.len(),
        )
        .map_err(|(path, problem)| SimConfigError::Invalid { path, problem })?;
        let now = clock.now();
        let card = Arc::new(SimCard {
            switches,
            epoch: now,
            seed: config.seed,
            ai: ai.into(),
            ao: ao.into(),
            di: BitImage::new(config.digital_inputs),
            di_held: BitImage::new(config.digital_inputs),
            dout: BitImage::new(config.digital_outputs),
            di_looped,
            step_state: Mutex::new(StepState {
                last_step: now,
                encoder_fraction: vec![0.0; encoders.len()],
            }),
            encoders: encoders.into(),
            fault: AtomicU8::new(FAULT_NONE),
            bus_error: ArcSwapOption::empty(),
            last_good: AtomicU64::new(0),
            record: (config.record_capacity > 0).then(|| OutputRecord::new(config.record_capacity)),
            clock,
        });
        card.step();
        Ok(card)
    }
}

fn group_scale(
    path: &str,
    range: &crate::config::RangeConfig,
    raw: device_interface::RawRange,
) -> Result<Scale, SimConfigError> {
    range.scale(raw).map_err(|source| SimConfigError::Scale {
        path: format!("{path}.range"),
        source,
    })
}

/// The fastest an encoder may count, counts per second: a day of motion (the longest
/// card period, so the most one step can move it) still fits the counter's 64 bits.
pub const MAX_COUNTS_PER_S: f64 = i64::MAX as f64 / 86_400.0;

/// Checks that encoder `e`'s motion is arithmetic that fits: `counts_per_unit` finite,
/// and the fastest it moves — the largest value of its velocity output times
/// `counts_per_unit` — within [`MAX_COUNTS_PER_S`] (beyond, a step's motion would
/// saturate the count and the turns with it).
fn check_speed(
    path: &str,
    e: &crate::config::EncoderConfig,
    ao: &[AnalogOutChannel],
) -> Result<(), SimConfigError> {
    let invalid = |problem: String| SimConfigError::Invalid {
        path: format!("{path}.counts_per_unit"),
        problem,
    };
    let k = e.counts_per_unit;
    if let Some(why) = device_interface::text::non_finite(k) {
        return Err(invalid(format!("{why}: give a finite number")));
    }
    let Some(out) = e.velocity_from.and_then(|ch| ao.get(ch as usize)) else {
        return Ok(());
    };
    let r = out.scale.range();
    let fastest = r.lowest.abs().max(r.highest.abs()) * k.abs();
    // Finite factors: no NaN here (an overflow is infinite, and too fast).
    if fastest > MAX_COUNTS_PER_S {
        let speed = if fastest.is_finite() {
            format!("up to {} counts/s", Number(fastest))
        } else {
            "more counts/s than any number".to_string()
        };
        return Err(invalid(format!(
            "{} counts/s per unit: over the velocity output's range {r} that is {speed}; \
             an encoder counts at most {} counts/s (a day of motion must fit its 64-bit \
             counter)",
            Number(k),
            Number(MAX_COUNTS_PER_S.floor())
        )));
    }
    Ok(())
}

fn check_waveform(
    path: &str,
    w: &Waveform,
    check_ao: &impl Fn(String, u32) -> Result<(), SimConfigError>,
) -> Result<(), SimConfigError> {
    let invalid = |key: &str, problem: String| SimConfigError::Invalid {
        path: format!("{path}.{key}"),
        problem,
    };
    let finite = |key: &str, v: f64| match device_interface::text::non_finite(v) {
        None => Ok(()),
        Some(why) => Err(invalid(key, format!("{why}: give a finite number"))),
    };
    // Sums and spans of finite numbers can still be beyond f64: every sample would then
    // be infinite or NaN.
    let fits = |key: &str, what: &str, v: f64| {
        if v.is_finite() {
            Ok(())
        } else {
            Err(invalid(
                key,
                format!("{what} overflows (beyond the largest number, about 1.8e308)"),
            ))
        }
    };
    match *w {
        Waveform::Constant { value } => finite("value", value),
        Waveform::Sine {
            amplitude,
            frequency,
            offset,
            phase,
        } => {
            finite("amplitude", amplitude)?;
            finite("offset", offset)?;
            finite("phase", phase)?;
            if !(frequency.is_finite() && frequency >= 0.0) {
                return Err(invalid(
                    "frequency",
                    format!("{} Hz: expected a frequency >= 0", Number(frequency)),
                ));
            }
            fits(
                "amplitude",
                "|offset| + |amplitude|",
                offset.abs() + amplitude.abs(),
            )?;
            fits(
                "frequency",
                "2π × frequency",
                std::f64::consts::TAU * frequency,
            )
        }
        Waveform::Ramp { from, to, period } => {
            finite("from", from)?;
            finite("to", to)?;
            if !(period.is_finite() && period > 0.0) {
                return Err(invalid(
                    "period",
                    format!("{} s: expected a period > 0", Number(period)),
                ));
            }
            fits("to", "to - from", to - from)
        }
        Waveform::Noise { mean, amplitude } => {
            finite("mean", mean)?;
            finite("amplitude", amplitude)?;
            fits(
                "amplitude",
                "|mean| + |amplitude|",
                mean.abs() + amplitude.abs(),
            )
        }
        Waveform::Loopback { analog_out } => check_ao(format!("{path}.analog_out"), analog_out),
    }
}

/// splitmix64: a well-mixed 64-bit hash of a 64-bit input, so noise at a given time and
/// channel depends only on the seed.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl SimCard {
    /// One bus cycle at the clock's current time: samples every input that is not held by a
    /// test hook, copies digital loopbacks, moves the encoders by their velocity since the
    /// last step, and marks the sample good. Does nothing to the inputs while the card is
    /// faulted (a stale or dead card delivers nothing new).
    pub fn step(&self) {
        let now = self.clock.now();
        let mut state = self.step_state.lock().unwrap_or_else(|p| p.into_inner());
        let dt = now.duration_since(state.last_step).as_secs_f64();
        state.last_step = now;

        // Encoders move whatever the bus does: the axis turns even when nobody reads it.
        for (i, enc) in self.encoders.iter().enumerate() {
            let Some(ch) = enc.velocity_from else {
                continue;
            };
            let velocity = self.ao_value(ch).unwrap_or(0.0) * enc.counts_per_unit;
            let moved = state.encoder_fraction[i] + velocity * dt;
            let whole = moved.trunc();
            state.encoder_fraction[i] = moved - whole;
            enc.counter.advance(whole as i64);
            enc.travel.fetch_add(whole as i64, Ordering::AcqRel);
        }

        if self.fault.load(Ordering::Acquire) != FAULT_NONE {
            return;
        }
        let t = now.duration_since(self.epoch).as_secs_f64();
        for (c, ch) in self.ai.iter().enumerate() {
            if ch.held.load(Ordering::Acquire) {
                continue;
            }
            let value = match ch.waveform {
                Waveform::Constant { value } => value,
                Waveform::Sine {
                    amplitude,
                    frequency,
                    offset,
                    phase,
                } => offset + amplitude * (std::f64::consts::TAU * frequency * t + phase).sin(),
                Waveform::Ramp { from, to, period } => from + (to - from) * (t / period).fract(),
                Waveform::Noise { mean, amplitude } => {
                    let h = mix(self.seed ^ mix(now.as_nanos() ^ mix(c as u64)));
                    // The top 53 bits give a uniform float in [0, 1).
                    let u = (h >> 11) as f64 / (1u64 << 53) as f64;
                    mean + amplitude * (2.0 * u - 1.0)
                }
                Waveform::Loopback { analog_out } => self.ao_value(analog_out).unwrap_or(0.0),
            };
            ch.raw
                .store(ch.scale.to_raw_saturating(value), Ordering::Release);
        }
        self.switches.apply(
            |e| self.encoders[e].travel.load(Ordering::Acquire),
            &self.di,
            &self.di_held,
        );
        // Looped bits follow the outputs unless a test holds them.
        self.di
            .copy_from(&self.dout, &self.di_looped, Some(&self.di_held));
        self.last_good
            .store(now.as_nanos().saturating_add(1), Ordering::Release);
    }

    fn ao_value(&self, channel: u32) -> Option<f64> {
        let ch = self.ao.get(channel as usize)?;
        Some(ch.scale.to_physical(ch.raw.load(Ordering::Acquire)))
    }

    fn last_good(&self) -> Option<Timestamp> {
        match self.last_good.load(Ordering::Acquire) {
            0 => None,
            n => Some(Timestamp::from_nanos(n - 1)),
        }
    }

    /// Fails as the simulated fault says, for an input (`stale_fails`) or an output.
    fn check_fault(&self, input: bool) -> Result<(), DeviceError> {
        match self.fault.load(Ordering::Acquire) {
            FAULT_NONE => Ok(()),
            FAULT_STALE if !input => Ok(()),
            FAULT_STALE => Err(DeviceError::Stale {
                age: self.last_good().map(|t| self.clock.now().duration_since(t)),
            }),
            FAULT_BUS => Err(self
                .bus_error
                .load()
                .as_deref()
                .cloned()
                .unwrap_or(DeviceError::Offline)),
            _ => Err(DeviceError::Offline),
        }
    }

    fn record(&self, write: OutputWrite) {
        if let Some(r) = &self.record {
            r.push(self.clock.now(), write);
        }
    }

    fn ai_channel(&self, channel: u32) -> Result<&AnalogInChannel, DeviceError> {
        device_interface::channel::nth(&self.ai, channel)
    }

    fn ao_channel(&self, channel: u32) -> Result<&AnalogOutChannel, DeviceError> {
        device_interface::channel::nth(&self.ao, channel)
    }

    // ---- test hooks ----

    /// Sets analog input `channel` to `raw` and holds it there (steps leave it alone) until
    /// [`release_analog_in`](Self::release_analog_in).
    pub fn set_analog_in_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let ch = self.ai_channel(channel)?;
        ch.scale.check_raw(channel, raw)?;
        ch.held.store(true, Ordering::Release);
        ch.raw.store(raw, Ordering::Release);
        Ok(())
    }

    /// Sets analog input `channel` to `value` (physical units, rounded to a raw step) and
    /// holds it, as [`set_analog_in_raw`](Self::set_analog_in_raw).
    pub fn set_analog_in(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        let raw = self
            .ai_channel(channel)?
            .scale
            .to_raw_checked(channel, value)?;
        self.set_analog_in_raw(channel, raw)
    }

    /// Lets analog input `channel` follow its waveform again from the next step.
    pub fn release_analog_in(&self, channel: u32) -> Result<(), DeviceError> {
        self.ai_channel(channel)?
            .held
            .store(false, Ordering::Release);
        Ok(())
    }

    /// Sets digital input `bit` and holds it (loopback leaves it alone) until
    /// [`release_digital_in`](Self::release_digital_in).
    pub fn set_digital_in(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.di_held.set(bit, true)?;
        self.di.set(bit, value).map(|_| ())
    }

    /// Lets digital input `bit` follow its loopback again from the next step.
    pub fn release_digital_in(&self, bit: u32) -> Result<(), DeviceError> {
        self.di_held.set(bit, false).map(|_| ())
    }

    /// Moves encoder `index` by `counts` (positive: the positive direction), as motion of
    /// the axis would.
    pub fn move_encoder(&self, index: usize, counts: i64) -> Result<(), DeviceError> {
        let enc = self
            .encoders
            .get(index)
            .ok_or(DeviceError::ChannelOutOfRange {
                channel: u32::try_from(index).unwrap_or(u32::MAX),
                count: self.encoders.len() as u32,
            })?;
        enc.counter.advance(counts);
        enc.travel.fetch_add(counts, Ordering::AcqRel);
        Ok(())
    }

    /// Simulates a fault, or clears it with [`SimFault::None`] (inputs are fresh again from
    /// the next step).
    pub fn set_fault(&self, fault: SimFault) {
        let code = match fault {
            SimFault::None => FAULT_NONE,
            SimFault::Stale => FAULT_STALE,
            SimFault::Offline => FAULT_OFFLINE,
            SimFault::Bus(text) => {
                self.bus_error
                    .store(Some(Arc::new(DeviceError::bus(SimulatedBusError(text)))));
                FAULT_BUS
            }
        };
        self.fault.store(code, Ordering::Release);
    }

    /// Takes the output writes recorded since the last call, oldest first. Empty when the
    /// card was built with `record_capacity = 0`.
    pub fn take_output_record(&self) -> Vec<OutputEvent> {
        self.record
            .as_ref()
            .map(OutputRecord::take)
            .unwrap_or_default()
    }

    /// Output writes recorded since the card was built (taken or not, dropped or not). Zero
    /// when the card was built with `record_capacity = 0`.
    pub fn output_writes(&self) -> u64 {
        self.record.as_ref().map_or(0, OutputRecord::count)
    }

    /// Output writes not recorded because the record was full.
    pub fn output_record_dropped(&self) -> u64 {
        self.record.as_ref().map_or(0, OutputRecord::dropped)
    }

    /// Number of simulated encoders.
    pub fn encoder_count(&self) -> usize {
        self.encoders.len()
    }

    /// Encoder `index` as a device of its own (an Orocos encoder is one axis).
    pub fn encoder(self: &Arc<Self>, index: usize) -> Option<Arc<SimEncoder>> {
        (index < self.encoders.len()).then(|| {
            Arc::new(SimEncoder {
                card: Arc::clone(self),
                index,
            })
        })
    }

    /// The card's devices, for [`Registry::register_card`]: every interface it has channels
    /// for, and each encoder as `encoder0`, `encoder1` …
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        CardDevices {
            analog_in: (!self.ai.is_empty()).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (!self.ao.is_empty()).then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: (!self.di.is_empty()).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (!self.dout.is_empty()).then(|| self.clone() as Arc<dyn DigitalOut>),
            drives: Vec::new(),
            encoders: (0..self.encoders.len())
                .filter_map(|i| {
                    self.encoder(i)
                        .map(|e| (format!("encoder{i}"), e as Arc<dyn Encoder>))
                })
                .collect(),
        }
    }

    /// Registers every interface the card has under `name` (`name.encoder0`, `name.encoder1`
    /// … for encoders), owned by `name`. On error nothing stays registered.
    pub fn register(
        self: &Arc<Self>,
        registry: &Registry,
        name: &str,
    ) -> Result<(), RegistryError> {
        registry.register_card(name, self.devices())
    }
}

impl Device for SimCard {
    fn health(&self) -> Health {
        let (status, last_error) = match self.fault.load(Ordering::Acquire) {
            FAULT_NONE => (Status::Online, None),
            FAULT_STALE => (Status::Stale, self.check_fault(true).err()),
            _ => (Status::Offline, self.check_fault(false).err()),
        };
        Health {
            status,
            last_good: self.last_good(),
            checked_at: self.clock.now(),
            last_error,
        }
    }
}

impl AnalogIn for SimCard {
    fn channel_count(&self) -> u32 {
        self.ai.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(self.ai_channel(channel)?.scale)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let ch = self.ai_channel(channel)?;
        self.check_fault(true)?;
        Ok(ch.raw.load(Ordering::Acquire))
    }
}

impl AnalogOut for SimCard {
    fn channel_count(&self) -> u32 {
        self.ao.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(self.ao_channel(channel)?.scale)
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let ch = self.ao_channel(channel)?;
        ch.scale.check_raw(channel, raw)?;
        self.check_fault(false)?;
        ch.raw.store(raw, Ordering::Release);
        self.record(OutputWrite::Analog { channel, raw });
        Ok(())
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        Ok(self.ao_channel(channel)?.raw.load(Ordering::Acquire))
    }
}

impl device_interface::bits::DigitalInputImage for SimCard {
    fn inputs(&self) -> &BitImage {
        &self.di
    }

    fn check_inputs(&self, _: BitSpan) -> Result<(), DeviceError> {
        self.check_fault(true)
    }
}

impl device_interface::bits::DigitalOutputImage for SimCard {
    fn outputs(&self) -> &BitImage {
        &self.dout
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.check_fault(false)
    }

    fn outputs_written(&self, written: device_interface::bits::Written) {
        use device_interface::bits::Written;
        self.record(match written {
            Written::Bit { bit, value } => OutputWrite::Bit { bit, value },
            Written::Span { span, value } => OutputWrite::Sequence {
                start: span.start(),
                stop: span.stop(),
                value,
            },
        });
    }
}

/// One encoder of a [`SimCard`], as a device of its own.
pub struct SimEncoder {
    card: Arc<SimCard>,
    index: usize,
}

impl SimEncoder {
    fn state(&self) -> &SimEncoderState {
        // `index` was checked when the handle was made and encoders never go away.
        &self.card.encoders[self.index]
    }
}

impl Device for SimEncoder {
    fn health(&self) -> Health {
        self.card.health()
    }
}

impl Encoder for SimEncoder {
    fn position(&self) -> Result<i64, DeviceError> {
        self.card.check_fault(true)?;
        Ok(self.state().counter.position())
    }

    fn turn(&self) -> Result<i64, DeviceError> {
        self.card.check_fault(true)?;
        Ok(self.state().counter.turn())
    }

    fn set_position(&self, position: i64) -> Result<(), DeviceError> {
        self.state().counter.geometry().check_position(position)?;
        self.card.check_fault(false)?;
        self.state().counter.set_position(position)?;
        self.card.record(OutputWrite::EncoderPosition {
            encoder: self.index as u32,
            position,
        });
        Ok(())
    }

    fn set_turn(&self, turn: i64) -> Result<(), DeviceError> {
        self.card.check_fault(false)?;
        self.state().counter.set_turn(turn)?;
        self.card.record(OutputWrite::EncoderTurn {
            encoder: self.index as u32,
            turn,
        });
        Ok(())
    }

    fn resolution(&self) -> i64 {
        self.state().counter.geometry().resolution()
    }

    fn upcounting(&self) -> bool {
        self.state().counter.geometry().upcounting()
    }
}
