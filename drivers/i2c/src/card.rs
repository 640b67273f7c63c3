//! An I2C card's devices: the chips' input pins, output pins, analog inputs and outputs as
//! one DigitalIn, DigitalOut, AnalogIn and AnalogOut, and their encoders, each chip's
//! channels after the previous chip's, in the section's order.
//!
//! Devices only touch images: `read_bit` answers from the last poll of the bit's chip,
//! `set_bit` records the level, marks the chip and wakes the bus side, which polls that
//! chip at once and sends it; `read_raw` answers an analog channel's last conversion
//! ([`DeviceError::Stale`] before its first). A channel of a chip that does not answer is
//! [`DeviceError::Offline`]. Real-time: no allocation, no lock; a write's one system call
//! is the bus side's wake-up (an `eventfd` write, which never blocks).

use device_interface::bits::BitImage;
use device_interface::channel::nth;
use device_interface::encoder::{CardEncoder, EncoderCounter, EncoderHost};
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, CardDevices, Device, DeviceError, DigitalIn, DigitalOut, Health, Scale,
    Status,
};
use rtt::activity::Waker;
use std::fmt;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// How many channels of each interface a chip adds to its card.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Shape {
    /// DigitalIn bits.
    pub digital_in: u32,
    /// DigitalOut bits.
    pub digital_out: u32,
}

/// A chip as the card is made of it: where it is, how often it is polled, its model's
/// name and channels.
#[derive(Debug, Clone)]
pub struct ChipPlace {
    /// Its address.
    pub address: u16,
    /// Poll period, ms.
    pub poll_ms: u32,
    /// Its model's name.
    pub model: &'static str,
    /// Its channels.
    pub shape: Shape,
    /// Its DigitalOut bits' levels from the start (one per bit; missing ones off).
    pub initial_on: Vec<bool>,
    /// Its analog inputs' scales (one per channel).
    pub analog_in: Vec<Scale>,
    /// Its analog outputs' scales and raw values from the start (one per channel).
    pub analog_out: Vec<(Scale, i64)>,
    /// Its encoders' resolution and counting direction (one per encoder).
    pub encoders: Vec<(i64, bool)>,
}

/// A raw analog value that was never read.
const NO_SAMPLE: i64 = i64::MIN;

/// One chip's place on the card and its state.
#[derive(Debug)]
pub struct ChipSlot {
    /// Its address.
    pub address: u16,
    /// Its model.
    pub model: &'static str,
    /// Poll period, ms.
    pub poll_ms: u32,
    pub(crate) digital_in: Range<u32>,
    pub(crate) digital_out: Range<u32>,
    pub(crate) analog_in: Range<u32>,
    pub(crate) analog_out: Range<u32>,
    pub(crate) encoders: Range<u32>,
    pub(crate) online: AtomicBool,
    /// Output writes the devices made (each one counts).
    pub(crate) wanted: AtomicU64,
    /// `wanted` as the chip model last took it to send.
    pub(crate) taken: AtomicU64,
    /// `wanted` as last sent: what the bus side confirms after a poll that succeeded.
    pub(crate) sent: AtomicU64,
    pub(crate) polls: AtomicU64,
    pub(crate) errors: AtomicU64,
    pub(crate) went_offline: AtomicU64,
    /// Times a poll or its check found it set up otherwise than its start left it (a power
    /// loss, a reset, another master) and it was set up again.
    pub(crate) resets: AtomicU64,
    /// What the last of those found.
    pub(crate) last_reset: Mutex<Option<Lost>>,
    pub(crate) last_good: AtomicU64,
    pub(crate) last_error: Mutex<Option<String>>,
}

impl ChipSlot {
    /// Whether a device wrote an output the chip's model has not taken to send yet.
    pub(crate) fn unsent(&self) -> bool {
        self.wanted.load(Ordering::Acquire) != self.taken.load(Ordering::Acquire)
    }

    /// Its poll period.
    pub(crate) fn period(&self) -> std::time::Duration {
        std::time::Duration::from_millis(u64::from(self.poll_ms))
    }
}

/// A snapshot of one chip's counters.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct ChipCounters {
    /// Its address.
    pub address: u16,
    /// Its model.
    pub model: &'static str,
    /// Whether it answers.
    pub online: bool,
    /// Polls that succeeded.
    pub polls: u64,
    /// Failed transfers (each one, transient or not).
    pub errors: u64,
    /// Times it stopped answering.
    pub went_offline: u64,
    /// Times it was found reset (or set up by someone else) and set up again.
    pub resets: u64,
    /// What the last of those found ("calibration reads 0x0000, not 0x1062").
    pub last_reset: Option<String>,
    /// Why it last failed.
    pub last_error: Option<String>,
}

/// The card's counters, for `hwgw status`.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct I2cCounters {
    /// Chips answering, of all.
    pub online: String,
    /// Each chip's.
    pub chips: Vec<ChipCounters>,
}

/// An I2C card.
pub struct I2cCard {
    pub(crate) chips: Vec<ChipSlot>,
    inputs: BitImage,
    outputs: BitImage,
    analog_raw: Box<[AtomicI64]>,
    analog_scale: Vec<Scale>,
    out_raw: Box<[AtomicI64]>,
    out_scale: Vec<Scale>,
    encoders: Vec<EncoderCounter>,
    clock: Arc<dyn Clock>,
    /// Wakes the bus side when an output is written (set once it runs).
    waker: OnceLock<Arc<dyn Waker>>,
}

/// What a chip model sees of the card: its own channels, numbered from 0.
pub struct ChipIo<'a> {
    card: &'a I2cCard,
    chip: &'a ChipSlot,
}

impl ChipIo<'_> {
    /// Records input `bit` of the chip as read.
    pub fn set_input(&self, bit: u32, value: bool) {
        let _ = self
            .card
            .inputs
            .set(self.chip.digital_in.start + bit, value);
    }

    /// The level output `bit` of the chip is to have.
    pub fn output(&self, bit: u32) -> bool {
        self.card
            .outputs
            .get(self.chip.digital_out.start + bit)
            .unwrap_or(false)
    }

    /// True, once, when a device changed an output of the chip since the last call.
    pub fn take_dirty(&self) -> bool {
        let wanted = self.chip.wanted.load(Ordering::Acquire);
        self.chip.taken.swap(wanted, Ordering::AcqRel) != wanted
    }

    /// Records analog input `channel` of the chip as converted.
    pub fn set_analog_in(&self, channel: u32, raw: i64) {
        if let Some(a) = self
            .card
            .analog_raw
            .get((self.chip.analog_in.start + channel) as usize)
        {
            a.store(raw, Ordering::Release);
        }
    }

    /// The raw value analog output `channel` of the chip is to have.
    pub fn analog_out(&self, channel: u32) -> i64 {
        self.card
            .out_raw
            .get((self.chip.analog_out.start + channel) as usize)
            .map_or(0, |a| a.load(Ordering::Acquire))
    }

    /// Encoder `index` of the chip.
    pub fn encoder(&self, index: u32) -> Option<&EncoderCounter> {
        self.card
            .encoders
            .get((self.chip.encoders.start + index) as usize)
    }

    /// Counts a reset the chip's model found, `lost` (the bus side sets the chip up
    /// again).
    pub fn count_reset(&self, lost: Lost) {
        *self
            .chip
            .last_reset
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(lost);
        self.chip.resets.fetch_add(1, Ordering::Relaxed);
    }

    /// The card's clock, now: for a model that times its chip (a conversion's deadline).
    pub fn now(&self) -> Timestamp {
        self.card.now()
    }

    /// Marks the chip's outputs as still to send (their write failed).
    pub fn mark_dirty(&self) {
        let sent = self.chip.sent.load(Ordering::Acquire);
        self.chip.taken.store(sent, Ordering::Release);
    }
}

impl I2cCard {
    /// A card of `places`, every chip offline until polled, outputs at each place's
    /// starting values. Fails on an encoder geometry the counter refuses.
    pub fn new(places: &[ChipPlace], clock: Arc<dyn Clock>) -> Result<I2cCard, DeviceError> {
        let (mut di, mut dout, mut ai, mut ao) = (0u32, 0u32, 0u32, 0u32);
        let mut analog_scale = Vec::new();
        let mut out = Vec::new();
        let mut encoders = Vec::new();
        let mut initial = Vec::new();
        let mut chips = Vec::with_capacity(places.len());
        for p in places {
            let Shape {
                digital_in,
                digital_out,
            } = p.shape;
            chips.push(ChipSlot {
                address: p.address,
                model: p.model,
                poll_ms: p.poll_ms,
                digital_in: di..di + digital_in,
                digital_out: dout..dout + digital_out,
                analog_in: ai..ai + p.analog_in.len() as u32,
                analog_out: ao..ao + p.analog_out.len() as u32,
                encoders: encoders.len() as u32..(encoders.len() + p.encoders.len()) as u32,
                online: AtomicBool::new(false),
                wanted: AtomicU64::new(0),
                taken: AtomicU64::new(0),
                sent: AtomicU64::new(0),
                polls: AtomicU64::new(0),
                errors: AtomicU64::new(0),
                went_offline: AtomicU64::new(0),
                resets: AtomicU64::new(0),
                last_reset: Mutex::new(None),
                last_good: AtomicU64::new(0),
                last_error: Mutex::new(None),
            });
            di += digital_in;
            dout += digital_out;
            initial.extend((0..digital_out as usize).map(|b| p.initial_on.get(b) == Some(&true)));
            ai += p.analog_in.len() as u32;
            ao += p.analog_out.len() as u32;
            analog_scale.extend(p.analog_in.iter().copied());
            out.extend(p.analog_out.iter().copied());
            for (resolution, upcounting) in &p.encoders {
                encoders.push(EncoderCounter::new(*resolution, *upcounting)?);
            }
        }
        let outputs = BitImage::new(dout);
        for (bit, on) in initial.iter().enumerate() {
            let _ = outputs.set(bit as u32, *on);
        }
        Ok(I2cCard {
            chips,
            inputs: BitImage::new(di),
            outputs,
            analog_raw: (0..ai).map(|_| AtomicI64::new(NO_SAMPLE)).collect(),
            analog_scale,
            out_raw: out.iter().map(|(_, raw)| AtomicI64::new(*raw)).collect(),
            out_scale: out.iter().map(|(scale, _)| *scale).collect(),
            encoders,
            clock,
            waker: OnceLock::new(),
        })
    }

    /// What chip `i`'s model sees.
    pub fn io(&self, i: usize) -> Option<ChipIo<'_>> {
        Some(ChipIo {
            card: self,
            chip: self.chips.get(i)?,
        })
    }

    /// The chips.
    pub fn chips(&self) -> &[ChipSlot] {
        &self.chips
    }

    /// The devices: a DigitalIn, a DigitalOut, an AnalogIn and an AnalogOut when the
    /// chips have such channels, and one Encoder each (`card.encoder0`, …).
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        CardDevices {
            digital_in: (!self.inputs.is_empty()).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (!self.outputs.is_empty()).then(|| self.clone() as Arc<dyn DigitalOut>),
            analog_in: (!self.analog_scale.is_empty()).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (!self.out_scale.is_empty()).then(|| self.clone() as Arc<dyn AnalogOut>),
            drives: Vec::new(),
            encoders: CardEncoder::all(self, self.encoders.len()),
        }
    }

    /// Its counters, now.
    pub fn counters(&self) -> I2cCounters {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let chips: Vec<ChipCounters> = self
            .chips
            .iter()
            .map(|c| ChipCounters {
                address: c.address,
                model: c.model,
                online: c.online.load(Ordering::Acquire),
                polls: l(&c.polls),
                errors: l(&c.errors),
                went_offline: l(&c.went_offline),
                resets: l(&c.resets),
                last_reset: c
                    .last_reset
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .map(|lost| lost.to_string()),
                last_error: c
                    .last_error
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .clone(),
            })
            .collect();
        I2cCounters {
            online: format!(
                "{}/{}",
                chips.iter().filter(|c| c.online).count(),
                chips.len()
            ),
            chips,
        }
    }

    /// Waits, until `deadline` at the latest, for every online chip's outputs written
    /// before the call to be sent (a poll that took them succeeded). Chips without outputs
    /// are not waited for. An error names each chip they may not have reached.
    pub fn settle(&self, deadline: std::time::Instant) -> Result<(), driver_api::SettleError> {
        let wanted: Vec<u64> = self
            .chips
            .iter()
            .map(|c| c.wanted.load(Ordering::Acquire))
            .collect();
        let has_outputs = |c: &ChipSlot| !c.digital_out.is_empty() || !c.analog_out.is_empty();
        let sent = |(c, w): (&ChipSlot, &u64)| {
            !has_outputs(c)
                || (c.online.load(Ordering::Acquire) && c.sent.load(Ordering::Acquire) >= *w)
        };
        driver_api::wait_while(deadline, std::time::Duration::from_millis(1), || {
            !self.chips.iter().zip(&wanted).all(sent)
        });
        let unsent: Vec<String> = self
            .chips
            .iter()
            .zip(&wanted)
            .filter(|(c, w)| !sent((c, w)))
            .map(|(c, _)| {
                let state = if c.online.load(Ordering::Acquire) {
                    "not sent in time"
                } else {
                    "offline"
                };
                format!("{} at {:#04x} ({state})", c.model, c.address)
            })
            .collect();
        if unsent.is_empty() {
            Ok(())
        } else {
            Err(driver_api::SettleError::Unsent(unsent))
        }
    }

    /// Sets what wakes the bus side when a device writes an output (once; later calls
    /// keep the first).
    pub fn set_waker(&self, waker: Arc<dyn Waker>) {
        let _ = self.waker.set(waker);
    }

    /// Records an output write to `chip` and wakes the bus side to send it.
    fn wanted(&self, chip: Option<&ChipSlot>) {
        if let Some(c) = chip {
            c.wanted.fetch_add(1, Ordering::AcqRel);
        }
        if let Some(w) = self.waker.get() {
            w.wake();
        }
    }

    pub(crate) fn now(&self) -> Timestamp {
        self.clock.now()
    }

    fn chip_of(&self, bit: u32, range: impl Fn(&ChipSlot) -> &Range<u32>) -> Option<&ChipSlot> {
        self.chips.iter().find(|c| range(c).contains(&bit))
    }

    fn online(c: Option<&ChipSlot>) -> Result<(), DeviceError> {
        match c {
            Some(c) if c.online.load(Ordering::Acquire) => Ok(()),
            _ => Err(DeviceError::Offline),
        }
    }
}

impl Device for I2cCard {
    fn health(&self) -> Health {
        let all = self.chips.iter().all(|c| c.online.load(Ordering::Acquire));
        let last = self
            .chips
            .iter()
            .map(|c| c.last_good.load(Ordering::Acquire))
            .filter(|t| *t != 0)
            .min();
        Health {
            status: if all { Status::Online } else { Status::Offline },
            last_good: last.map(Timestamp::from_nanos),
            checked_at: self.clock.now(),
            last_error: (!all).then_some(DeviceError::Offline),
        }
    }
}

impl DigitalIn for I2cCard {
    fn input_count(&self) -> u32 {
        self.inputs.len()
    }

    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.inputs.check_bit(bit)?;
        Self::online(self.chip_of(bit, |c| &c.digital_in))?;
        self.inputs.get(bit)
    }
}

impl DigitalOut for I2cCard {
    fn output_count(&self) -> u32 {
        self.outputs.len()
    }

    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.outputs.check_bit(bit)?;
        let chip = self.chip_of(bit, |c| &c.digital_out);
        Self::online(chip)?;
        self.outputs.set(bit, value)?;
        self.wanted(chip);
        Ok(())
    }

    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.outputs.check_bit(bit)?;
        Self::online(self.chip_of(bit, |c| &c.digital_out))?;
        self.outputs.get(bit)
    }
}

impl AnalogIn for I2cCard {
    fn channel_count(&self) -> u32 {
        self.analog_scale.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        nth(&self.analog_scale, channel).copied()
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        AnalogIn::scale(self, channel)?;
        Self::online(self.chip_of(channel, |c| &c.analog_in))?;
        match self.analog_raw[channel as usize].load(Ordering::Acquire) {
            NO_SAMPLE => Err(DeviceError::Stale { age: None }),
            raw => Ok(raw),
        }
    }
}

impl AnalogOut for I2cCard {
    fn channel_count(&self) -> u32 {
        self.out_scale.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        nth(&self.out_scale, channel).copied()
    }

    /// Recorded, and the chip's poll that sends it asked for at once.
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        AnalogOut::scale(self, channel)?.check_raw(channel, raw)?;
        let chip = self.chip_of(channel, |c| &c.analog_out);
        Self::online(chip)?;
        self.out_raw[channel as usize].store(raw, Ordering::Release);
        self.wanted(chip);
        Ok(())
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        AnalogOut::scale(self, channel)?;
        Ok(self.out_raw[channel as usize].load(Ordering::Acquire))
    }
}

impl EncoderHost for I2cCard {
    fn encoder_counter(&self, index: usize) -> &EncoderCounter {
        &self.encoders[index]
    }

    fn check_encoder(&self, index: usize) -> Result<(), DeviceError> {
        Self::online(self.chip_of(index as u32, |c| &c.encoders))
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// A register a chip model found otherwise than it set it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lost {
    /// The register, as the datasheet names it.
    pub register: &'static str,
    /// What it reads (as the datasheet writes it: MSB first).
    pub found: u16,
    /// What the model set.
    pub wanted: u16,
}

impl Lost {
    /// The difference, if `found` is not `wanted`.
    pub fn compare(register: &'static str, found: u16, wanted: u16) -> Option<Lost> {
        (found != wanted).then_some(Lost {
            register,
            found,
            wanted,
        })
    }
}

impl fmt::Display for Lost {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} reads {:#06x}, not {:#06x}",
            self.register, self.found, self.wanted
        )
    }
}
