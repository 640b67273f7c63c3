//! A GPIO card's devices: its input lines as DigitalIn bits, its output lines as
//! DigitalOut bits, its quadrature encoders as Encoder devices.
//!
//! The card is built from resolved lines (nothing requested: `hwgw check` must not drive an
//! output) and requests them at [`GpioBus::open`](crate::bus::GpioBus::open), one request
//! per chip: output lines at their initial value from the request on, inputs with their
//! bias, polarity, debounce period and edge detection. Until then, and after its chip went
//! away, every device call fails with [`DeviceError::Offline`]. A chip that goes away (an
//! unplugged USB adapter) takes the card offline until the bus side finds it again and
//! requests its lines anew, outputs at the level last written (see
//! [`GpioBus`](crate::bus::GpioBus)).
//!
//! Each chip's request sits behind a mutex of its own: a device call holds it for its one
//! ioctl and the update of the output image, the bus side for one non-blocking read, and
//! for closing or replacing the request. So no call reaches a descriptor that was closed or
//! reused, and the image a chip is requested again with is the level its line last had.
//!
//! Real-time paths: `read_bit` of an input with edge detection on both edges answers from
//! the line's state the edge events keep (no ioctl, no lock); other inputs are one
//! `GPIO_V2_LINE_GET_VALUES` ioctl; `set_bit` and `set_sequence` over the lines of one chip
//! are one `GPIO_V2_LINE_SET_VALUES` ioctl; each under its chip's mutex (std's: no priority
//! inheritance — a low-priority thread writing the same chip can delay a high-priority
//! one by one ioctl). None allocates but on an error path.

use crate::chips::LineId;
use crate::config::{Bias, Drive, Edges};
use device_interface::bits::BitSpan;
use device_interface::encoder::{CardEncoder, EncoderCounter, EncoderHost};
use device_interface::time::Clock;
use device_interface::{CardDevices, Device, DeviceError, DigitalIn, DigitalOut, Health};
use gpiocdev_uapi::v2::{LineValues, get_line_values, set_line_values};
use std::fs::File;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

/// How one line is requested.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Setup {
    /// An input.
    Input {
        /// Bias.
        bias: Bias,
        /// Active low.
        active_low: bool,
        /// Debounce period, µs.
        debounce_us: u32,
        /// Edge detection.
        edges: Edges,
    },
    /// An output.
    Output {
        /// Drive.
        drive: Drive,
        /// Bias.
        bias: Bias,
        /// Active low.
        active_low: bool,
        /// Logical value from the request on.
        initial: bool,
    },
}

/// A line of the card: where it is and how it is requested.
#[derive(Debug, Clone)]
pub struct Line {
    /// The line.
    pub id: LineId,
    /// Its request.
    pub setup: Setup,
}

/// Which line of the card (index into its chip's request) an input, output or encoder
/// uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Slot {
    /// Index of the chip among the card's chips.
    pub chip: usize,
    /// Index of the line in the chip's request (its bit in line values).
    pub bit: u32,
}

/// The lines of one chip, in request order.
#[derive(Debug)]
pub(crate) struct ChipLines {
    pub lines: Vec<Line>,
}

/// A chip's request, once made.
pub(crate) struct Opened {
    /// The request (owns the line fd; kept so the lines stay requested).
    pub _request: gpiocdev::Request,
    /// The same fd, non-blocking, for allocation-free ioctls and reads.
    pub file: File,
    /// The chip it was made on, as found then (a chip that came back may have a new
    /// number).
    pub chip: crate::chips::ChipId,
}

/// Counters of a card.
#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub events: AtomicU64,
    pub lost_events: AtomicU64,
    pub encoder_errors: AtomicU64,
    pub index_pulses: AtomicU64,
    pub read_errors: AtomicU64,
    pub write_errors: AtomicU64,
    pub chips_lost: AtomicU64,
    pub chips_back: AtomicU64,
}

/// A snapshot of a card's counters, for `hwgw status`.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct GpioCounters {
    /// Whether its lines are requested and its chips present.
    pub online: bool,
    /// Edge events read.
    pub events: u64,
    /// Edge events the kernel dropped (gaps in the lines' sequence numbers: a full event
    /// buffer) or that the card could not read.
    pub lost_events: u64,
    /// Impossible quadrature transitions (an encoder lost edges).
    pub encoder_errors: u64,
    /// Index pulses seen.
    pub index_pulses: u64,
    /// Failed line reads.
    pub read_errors: u64,
    /// Failed line writes.
    pub write_errors: u64,
    /// Times a chip of the card went away.
    pub chips_lost: u64,
    /// Times a chip that went away was found again and its lines requested anew.
    pub chips_back: u64,
}

/// One encoder's lines and count.
pub(crate) struct Enc {
    pub a: Slot,
    pub b: Slot,
    pub index: Option<Slot>,
    pub counter: EncoderCounter,
}

/// A GPIO card.
pub struct GpioCard {
    pub(crate) consumer: String,
    pub(crate) event_buffer: Option<u32>,
    pub(crate) chips: Vec<ChipLines>,
    pub(crate) inputs: Vec<(Slot, Edges)>,
    /// The state of each input with edge detection on both edges, kept by the events.
    pub(crate) input_state: Vec<AtomicBool>,
    pub(crate) outputs: Vec<Slot>,
    pub(crate) output_image: Vec<AtomicBool>,
    pub(crate) encoders: Vec<Enc>,
    /// Each chip's request, while it is made and the chip is there (see the module doc).
    pub(crate) opened: Vec<Mutex<Option<Opened>>>,
    pub(crate) online: AtomicBool,
    pub(crate) last_event: AtomicU64,
    pub(crate) counters: Counters,
    pub(crate) clock: Arc<dyn Clock>,
}

/// True for the error of a request whose chip is gone (`ENODEV`).
pub(crate) fn is_gone(e: &gpiocdev_uapi::Error) -> bool {
    matches!(e, gpiocdev_uapi::Error::Os(gpiocdev_uapi::Errno(n)) if *n == nix::errno::Errno::ENODEV as i32)
}

fn bus_error(e: gpiocdev_uapi::Error) -> DeviceError {
    DeviceError::Bus {
        source: Arc::new(e),
    }
}

impl GpioCard {
    /// Its counters, now.
    pub fn counters(&self) -> GpioCounters {
        let c = &self.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        GpioCounters {
            online: self.online.load(Ordering::Acquire),
            events: l(&c.events),
            lost_events: l(&c.lost_events),
            encoder_errors: l(&c.encoder_errors),
            index_pulses: l(&c.index_pulses),
            read_errors: l(&c.read_errors),
            write_errors: l(&c.write_errors),
            chips_lost: l(&c.chips_lost),
            chips_back: l(&c.chips_back),
        }
    }

    /// The names of the card's chips: as requested now, or as found at build for one not
    /// requested (yet, or since it went away).
    pub fn chip_names(&self) -> Vec<String> {
        self.chips
            .iter()
            .enumerate()
            .map(|(i, c)| match self.request(i).as_deref() {
                Some(Some(o)) => o.chip.name.clone(),
                _ => c.lines[0].id.chip.name.clone(),
            })
            .collect()
    }

    /// Every line of the card, chip by chip.
    pub fn lines(&self) -> impl Iterator<Item = &Line> {
        self.chips.iter().flat_map(|c| &c.lines)
    }

    /// The line behind input `bit`, output `bit`.
    pub fn input_line(&self, bit: u32) -> Option<&Line> {
        let (s, _) = self.inputs.get(bit as usize)?;
        self.line(*s)
    }

    /// The line behind output `bit`.
    pub fn output_line(&self, bit: u32) -> Option<&Line> {
        self.line(*self.outputs.get(bit as usize)?)
    }

    pub(crate) fn line(&self, s: Slot) -> Option<&Line> {
        self.chips.get(s.chip)?.lines.get(s.bit as usize)
    }

    /// The devices: DigitalIn and DigitalOut when it has such lines, one Encoder each
    /// (`card.encoder0`, `card.encoder1`, …).
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        CardDevices {
            digital_in: (!self.inputs.is_empty()).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (!self.outputs.is_empty()).then(|| self.clone() as Arc<dyn DigitalOut>),
            drives: Vec::new(),
            encoders: CardEncoder::all(self, self.encoders.len()),
            ..CardDevices::default()
        }
    }

    /// `chip`'s request slot, locked.
    pub(crate) fn request(&self, chip: usize) -> Option<MutexGuard<'_, Option<Opened>>> {
        Some(
            self.opened
                .get(chip)?
                .lock()
                .unwrap_or_else(PoisonError::into_inner),
        )
    }

    /// Runs `f` on `chip`'s request under its lock, when it is made (online or not: the
    /// bus side reads where lines stand before the card goes online).
    pub(crate) fn with_request<R>(
        &self,
        chip: usize,
        f: impl FnOnce(&File) -> R,
    ) -> Result<R, DeviceError> {
        match self.request(chip).as_deref() {
            Some(Some(o)) => Ok(f(&o.file)),
            _ => Err(DeviceError::Offline),
        }
    }

    /// True when the card is online.
    fn check_online(&self) -> Result<(), DeviceError> {
        if self.online.load(Ordering::Acquire) {
            Ok(())
        } else {
            Err(DeviceError::Offline)
        }
    }

    /// Counts a failed ioctl; a chip that is gone (ENODEV) takes the card offline at once
    /// (the bus side finds the loss too and closes the request). Called with the chip's
    /// lock held, so the bus side cannot have put the card online again in between.
    fn failed(&self, e: gpiocdev_uapi::Error, counter: &AtomicU64) -> DeviceError {
        counter.fetch_add(1, Ordering::Relaxed);
        if is_gone(&e) {
            self.online.store(false, Ordering::Release);
        }
        bus_error(e)
    }

    /// Reads the lines `mask` of `chip` (one ioctl), when online.
    pub(crate) fn get(&self, chip: usize, mask: u64) -> Result<u64, DeviceError> {
        self.with_request(chip, |f| {
            self.check_online()?;
            self.read_lines(f, mask)
        })?
    }

    /// Reads the lines `mask` of `chip` while the card is not online yet.
    pub(crate) fn get_unchecked(&self, chip: usize, mask: u64) -> Result<u64, DeviceError> {
        self.with_request(chip, |f| self.read_lines(f, mask))?
    }

    fn read_lines(&self, f: &File, mask: u64) -> Result<u64, DeviceError> {
        let mut lv = LineValues { bits: 0, mask };
        get_line_values(f, &mut lv).map_err(|e| self.failed(e, &self.counters.read_errors))?;
        Ok(lv.bits & mask)
    }

    /// Sets the lines `mask` of `chip` to `bits` (one ioctl), then, still under the chip's
    /// lock, runs `then` (which records the levels in the output image).
    fn set(
        &self,
        chip: usize,
        mask: u64,
        bits: u64,
        then: impl FnOnce(),
    ) -> Result<(), DeviceError> {
        self.with_request(chip, |f| {
            self.check_online()?;
            set_line_values(f, &LineValues { bits, mask })
                .map_err(|e| self.failed(e, &self.counters.write_errors))?;
            then();
            Ok(())
        })?
    }

    /// The logical level output line `line` of `chip` is to have when (re)requested: the
    /// last value written, or its initial value.
    pub(crate) fn output_level(&self, chip: usize, line: u32) -> Option<bool> {
        let bit = self
            .outputs
            .iter()
            .position(|s| s.chip == chip && s.bit == line)?;
        Some(self.output_image[bit].load(Ordering::Acquire))
    }

    fn input(&self, bit: u32) -> Result<(Slot, Edges), DeviceError> {
        self.inputs
            .get(bit as usize)
            .copied()
            .ok_or(DeviceError::BitOutOfRange {
                bit,
                count: self.input_count(),
            })
    }

    fn output(&self, bit: u32) -> Result<Slot, DeviceError> {
        self.outputs
            .get(bit as usize)
            .copied()
            .ok_or(DeviceError::BitOutOfRange {
                bit,
                count: self.output_count(),
            })
    }
}

impl Device for GpioCard {
    fn health(&self) -> Health {
        Health::online_if(
            self.online.load(Ordering::Acquire),
            self.last_event.load(Ordering::Acquire),
            self.clock.now(),
        )
    }
}

impl DigitalIn for GpioCard {
    fn input_count(&self) -> u32 {
        self.inputs.len() as u32
    }

    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        let (slot, edges) = self.input(bit)?;
        if edges == Edges::Both {
            self.check_online()?;
            return Ok(self.input_state[bit as usize].load(Ordering::Acquire));
        }
        Ok(self.get(slot.chip, 1 << slot.bit)? != 0)
    }
}

impl DigitalOut for GpioCard {
    fn output_count(&self) -> u32 {
        self.outputs.len() as u32
    }

    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        let slot = self.output(bit)?;
        self.set(
            slot.chip,
            1 << slot.bit,
            u64::from(value) << slot.bit,
            || {
                self.output_image[bit as usize].store(value, Ordering::Release);
            },
        )
    }

    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.output(bit)?;
        self.check_online()?;
        Ok(self.output_image[bit as usize].load(Ordering::Acquire))
    }

    /// One ioctl per chip the span's lines are on (one for lines of one chip).
    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = BitSpan::new(start, stop, self.output_count())?;
        span.check_value(value)?;
        for chip in 0..self.chips.len() {
            let (mut mask, mut bits) = (0u64, 0u64);
            for (bit, i) in span.bits() {
                let s = self.outputs[bit as usize];
                if s.chip == chip {
                    mask |= 1 << s.bit;
                    bits |= (value >> i & 1) << s.bit;
                }
            }
            if mask != 0 {
                self.set(chip, mask, bits, || {
                    for (bit, i) in span.bits() {
                        if self.outputs[bit as usize].chip == chip {
                            self.output_image[bit as usize]
                                .store(value >> i & 1 == 1, Ordering::Release);
                        }
                    }
                })?;
            }
        }
        Ok(())
    }
}

impl EncoderHost for GpioCard {
    fn encoder_counter(&self, index: usize) -> &EncoderCounter {
        &self.encoders[index].counter
    }

    fn check_encoder(&self, _index: usize) -> Result<(), DeviceError> {
        self.check_online()
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        self.check_online()
    }
}
