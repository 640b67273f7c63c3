//! A comedi card's devices: its analog inputs and outputs, digital inputs and outputs and
//! counters as one AnalogIn, AnalogOut, DigitalIn, DigitalOut and an Encoder each.
//!
//! Inputs are sampled by the bus side every poll period ([`ComediBus`](crate::bus::ComediBus)):
//! `read_raw` and `read_bit` answer the last sample (no system call, no lock;
//! [`DeviceError::Stale`] before the first, and after a range change until the next poll).
//! Outputs go to the board at once: `set_bit` is one `comedi_dio_bitfield2`, `set_sequence`
//! one per subdevice window of 32 channels it spans, `write_raw` one `comedi_data_write`,
//! each under the board's mutex (std's: no priority inheritance; the bus side holds it for
//! one call at a time, so a write waits at most one sample's `ioctl`). None allocates but on
//! an error path. Until the board is open, and after it went away, every call fails with
//! [`DeviceError::Offline`].

use crate::board::{ComediError, Daq};
use crate::layout::{AnalogChan, BitChan, Layout};
use device_interface::bits::{BitImage, BitSpan};
use device_interface::channel::nth;
use device_interface::encoder::{CardEncoder, EncoderCounter, EncoderHost, WrappingCounter};
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, AnalogReference, CardDevices, Device, DeviceError, DigitalIn, DigitalOut,
    Health, Scale,
};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

/// No sample (the packed sample's valid bit clear).
const NO_SAMPLE: u64 = 0;
const VALID: u64 = 1 << 63;

/// A sample and the range and reference it was taken in, in one word: valid bit, aref
/// (bits 48–49), range (bits 32–47), raw.
pub(crate) fn pack(raw: u32, range: u32, aref: u32) -> u64 {
    VALID | (u64::from(aref & 3) << 48) | (u64::from(range & 0xffff) << 32) | u64::from(raw)
}

/// (raw, range, aref) of a packed sample, if valid.
pub(crate) fn unpack(word: u64) -> Option<(u32, u32, u32)> {
    (word & VALID != 0).then_some((
        (word & 0xffff_ffff) as u32,
        ((word >> 32) & 0xffff) as u32,
        ((word >> 48) & 3) as u32,
    ))
}

/// An analog input channel's state.
#[derive(Debug)]
pub(crate) struct AiSlot {
    pub(crate) chan: AnalogChan,
    pub(crate) range: AtomicU32,
    pub(crate) aref: AtomicU32,
    pub(crate) sample: AtomicU64,
}

/// An analog output channel's state.
#[derive(Debug)]
pub(crate) struct AoSlot {
    pub(crate) chan: AnalogChan,
    /// The value it has (packed as a sample), once known.
    pub(crate) value: AtomicU64,
    /// Whether hwgw wrote it (or its initial value is configured): written again when the
    /// board comes back.
    pub(crate) asked: AtomicBool,
}

/// A digital output's state.
#[derive(Debug)]
pub(crate) struct DoSlot {
    pub(crate) chan: BitChan,
    /// Its level is known (read from the board, configured, or written).
    pub(crate) known: AtomicBool,
    /// hwgw wrote it (or its initial level is configured).
    pub(crate) asked: AtomicBool,
}

/// The card's counters, for `hwgw status`.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct ComediCounters {
    /// The board (driver, board name) as found at build.
    pub board: String,
    /// Whether it is open and answering.
    pub online: bool,
    /// Polls that read every input.
    pub polls: u64,
    /// Failed calls (each one, polls and writes).
    pub errors: u64,
    /// Times it went away.
    pub went_offline: u64,
    /// Times it was opened (the first included).
    pub opened: u64,
    /// Why it last failed.
    pub last_error: Option<String>,
}

/// A comedi card.
pub struct ComediCard {
    pub(crate) path: String,
    pub(crate) name: String,
    pub(crate) board: Mutex<Option<Box<dyn Daq>>>,
    pub(crate) online: AtomicBool,
    /// The inputs were read since the board was last opened.
    pub(crate) fresh: AtomicBool,
    /// The gateway is stopping: the board is not opened again (see `settle`).
    pub(crate) closing: AtomicBool,
    pub(crate) ai: Vec<AiSlot>,
    pub(crate) ao: Vec<AoSlot>,
    pub(crate) di: Vec<BitChan>,
    pub(crate) dout: Vec<DoSlot>,
    pub(crate) inputs: BitImage,
    pub(crate) outputs: BitImage,
    pub(crate) counters: Vec<(crate::layout::CounterChan, WrappingCounter)>,
    pub(crate) polls: AtomicU64,
    pub(crate) errors: AtomicU64,
    pub(crate) went_offline: AtomicU64,
    pub(crate) opened: AtomicU64,
    pub(crate) last_good: AtomicU64,
    pub(crate) last_error: Mutex<Option<String>>,
    clock: Arc<dyn Clock>,
}

impl ComediCard {
    /// A card over `layout` of the board at `path` (`name` is its driver and board name,
    /// for status), offline until the bus side opens it. Fails on a counter geometry the
    /// encoder refuses.
    pub fn new(
        path: &str,
        name: &str,
        layout: Layout,
        clock: Arc<dyn Clock>,
    ) -> Result<ComediCard, DeviceError> {
        let analog = layout.analog_in.iter().chain(&layout.analog_out);
        if analog
            .clone()
            .any(|c| c.ranges.get(c.range as usize).is_none())
        {
            return Err(DeviceError::Unsupported {
                what: "an analog channel without its starting range in its range table",
            });
        }
        let counters = layout
            .counters
            .iter()
            .map(|c| {
                let bits = 32 - c.maxdata.leading_zeros();
                WrappingCounter::new(c.resolution, c.upcounting, bits.max(1)).map(|w| (*c, w))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let outputs = BitImage::new(layout.output.len() as u32);
        Ok(ComediCard {
            path: path.to_string(),
            name: name.to_string(),
            board: Mutex::new(None),
            online: AtomicBool::new(false),
            fresh: AtomicBool::new(false),
            closing: AtomicBool::new(false),
            ai: layout
                .analog_in
                .into_iter()
                .map(|chan| AiSlot {
                    range: AtomicU32::new(chan.range),
                    aref: AtomicU32::new(chan.aref.raw()),
                    sample: AtomicU64::new(NO_SAMPLE),
                    chan,
                })
                .collect(),
            ao: layout
                .analog_out
                .into_iter()
                .map(|chan| AoSlot {
                    value: AtomicU64::new(
                        chan.initial
                            .map_or(NO_SAMPLE, |r| pack(r, chan.range, chan.aref.raw())),
                    ),
                    asked: AtomicBool::new(chan.initial.is_some()),
                    chan,
                })
                .collect(),
            inputs: BitImage::new(layout.input.len() as u32),
            di: layout.input,
            dout: layout
                .output
                .into_iter()
                .enumerate()
                .map(|(i, chan)| {
                    if let Some(on) = chan.initial {
                        let _ = outputs.set(i as u32, on);
                    }
                    DoSlot {
                        known: AtomicBool::new(chan.initial.is_some()),
                        asked: AtomicBool::new(chan.initial.is_some()),
                        chan,
                    }
                })
                .collect(),
            outputs,
            counters,
            polls: AtomicU64::new(0),
            errors: AtomicU64::new(0),
            went_offline: AtomicU64::new(0),
            opened: AtomicU64::new(0),
            last_good: AtomicU64::new(0),
            last_error: Mutex::new(None),
            clock,
        })
    }

    /// The devices: an AnalogIn, AnalogOut, DigitalIn and DigitalOut when the section maps
    /// such channels, and one Encoder per counter (`card.encoder0`, …).
    pub fn devices(self: &Arc<Self>) -> CardDevices {
        CardDevices {
            analog_in: (!self.ai.is_empty()).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (!self.ao.is_empty()).then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: (!self.di.is_empty()).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (!self.dout.is_empty()).then(|| self.clone() as Arc<dyn DigitalOut>),
            drives: Vec::new(),
            encoders: CardEncoder::all(self, self.counters.len()),
        }
    }

    /// Its path.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// Whether the board is open and answering.
    pub fn is_online(&self) -> bool {
        self.online.load(Ordering::Acquire)
    }

    /// Polls that read every input, so far.
    pub fn polls(&self) -> u64 {
        self.polls.load(Ordering::Relaxed)
    }

    /// Its counters, now.
    pub fn counters(&self) -> ComediCounters {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        ComediCounters {
            board: self.name.clone(),
            online: self.is_online(),
            polls: l(&self.polls),
            errors: l(&self.errors),
            went_offline: l(&self.went_offline),
            opened: l(&self.opened),
            last_error: self
                .last_error
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .clone(),
        }
    }

    /// At stop, after the gateway wrote the safe values (at once, as every write): the
    /// board is not opened again from now on, so a board that comes back before the bus
    /// side stops is not given the outputs it had before. `Err` when it is offline: the
    /// safe values could not be written.
    pub fn settle(&self) -> Result<(), driver_api::SettleError> {
        self.closing.store(true, Ordering::Release);
        if self.is_online() {
            Ok(())
        } else {
            Err(driver_api::SettleError::Offline(self.path.clone()))
        }
    }

    pub(crate) fn lock(&self) -> MutexGuard<'_, Option<Box<dyn Daq>>> {
        self.board.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Records a failed call; a board gone takes the card offline (the bus side closes
    /// and opens it again).
    pub(crate) fn failed(&self, e: &ComediError) {
        self.errors.fetch_add(1, Ordering::Relaxed);
        // The error first: whoever sees the card offline finds why.
        *self
            .last_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(e.to_string());
        if e.gone() && self.online.swap(false, Ordering::AcqRel) {
            self.went_offline.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Runs `f` on the open board; Offline when there is none, a failed call recorded.
    fn with_board<T>(
        &self,
        f: impl FnOnce(&mut dyn Daq) -> Result<T, ComediError>,
    ) -> Result<T, DeviceError> {
        if !self.is_online() {
            return Err(DeviceError::Offline);
        }
        let mut board = self.lock();
        let Some(b) = board.as_mut() else {
            return Err(DeviceError::Offline);
        };
        f(b.as_mut()).map_err(|e| {
            self.failed(&e);
            if e.gone() {
                DeviceError::Offline
            } else {
                DeviceError::bus(e)
            }
        })
    }

    pub(crate) fn now(&self) -> Timestamp {
        self.clock.now()
    }

    fn ai(&self, channel: u32) -> Result<&AiSlot, DeviceError> {
        nth(&self.ai, channel)
    }

    fn ao(&self, channel: u32) -> Result<&AoSlot, DeviceError> {
        nth(&self.ao, channel)
    }

    /// Writes outputs `start..=stop` (at most 64, checked) to the bits of `value` (the
    /// lowest for `start`): one bit-field call per subdevice window of 32 channels.
    fn write_bits(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = move || (start..=stop).map(move |b| (b, value >> (b - start) & 1 == 1));
        // A span has at most 64 bits, so at most 64 windows; no allocation.
        let mut windows = [(0u32, 0u32, 0u32, 0u32); 64];
        let mut n = 0;
        for (bit, on) in span() {
            let c = &self.dout[bit as usize].chan;
            let base = c.channel & !31;
            let shift = 1u32 << (c.channel - base);
            let w = match windows[..n]
                .iter()
                .position(|w| w.0 == c.subdevice && w.1 == base)
            {
                Some(w) => w,
                None if n < windows.len() => {
                    windows[n] = (c.subdevice, base, 0, 0);
                    n += 1;
                    n - 1
                }
                None => {
                    return Err(DeviceError::Unsupported {
                        what: "more than 64 output windows",
                    });
                }
            };
            windows[w].2 |= shift;
            if on {
                windows[w].3 |= shift;
            }
        }
        // Each window's outputs recorded under the board's lock as soon as it is written:
        // what a reopen writes back, and what the read-back says, is what the board has.
        self.with_board(|b| {
            for &(sub, base, mask, bits) in &windows[..n] {
                b.bitfield(sub, base, mask, bits)?;
                for (bit, on) in span() {
                    let slot = &self.dout[bit as usize];
                    if slot.chan.subdevice == sub && slot.chan.channel & !31 == base {
                        let _ = self.outputs.set(bit, on);
                        slot.known.store(true, Ordering::Release);
                        slot.asked.store(true, Ordering::Release);
                    }
                }
            }
            Ok(())
        })
    }
}

impl Device for ComediCard {
    fn health(&self) -> Health {
        Health::online_if(
            self.is_online(),
            self.last_good.load(Ordering::Acquire),
            self.clock.now(),
        )
    }
}

impl AnalogIn for ComediCard {
    fn channel_count(&self) -> u32 {
        self.ai.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        let a = self.ai(channel)?;
        // `new` checked every channel has its starting range; `select_range` stores only
        // indices in the table.
        let r = a.range.load(Ordering::Acquire) as usize;
        a.chan
            .ranges
            .get(r)
            .map(|(_, scale)| *scale)
            .ok_or(DeviceError::Unsupported {
                what: "a channel without that range",
            })
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let a = self.ai(channel)?;
        if !self.is_online() {
            return Err(DeviceError::Offline);
        }
        match unpack(a.sample.load(Ordering::Acquire)) {
            Some((raw, range, aref))
                if range == a.range.load(Ordering::Acquire)
                    && aref == a.aref.load(Ordering::Acquire) =>
            {
                Ok(i64::from(raw))
            }
            _ => Err(DeviceError::Stale { age: None }),
        }
    }

    fn range_count(&self, channel: u32) -> Result<u32, DeviceError> {
        Ok(self.ai(channel)?.chan.ranges.len() as u32)
    }

    /// Takes effect at the next poll; until then `read_raw` is stale.
    fn select_range(&self, channel: u32, index: u32) -> Result<(), DeviceError> {
        let a = self.ai(channel)?;
        if index as usize >= a.chan.ranges.len() {
            return Err(DeviceError::Unsupported {
                what: "a range index past the channel's range table",
            });
        }
        a.range.store(index, Ordering::Release);
        Ok(())
    }

    fn select_reference(
        &self,
        channel: u32,
        reference: AnalogReference,
    ) -> Result<(), DeviceError> {
        let a = self.ai(channel)?;
        let aref = match reference {
            AnalogReference::Ground => crate::config::Aref::Ground,
            AnalogReference::Common => crate::config::Aref::Common,
            AnalogReference::Differential => crate::config::Aref::Diff,
            AnalogReference::Other => crate::config::Aref::Other,
        };
        if a.chan.flags & aref.flag() == 0 {
            return Err(DeviceError::Unsupported {
                what: "this reference on this subdevice",
            });
        }
        a.aref.store(aref.raw(), Ordering::Release);
        Ok(())
    }
}

impl AnalogOut for ComediCard {
    fn channel_count(&self) -> u32 {
        self.ao.len() as u32
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        let a = self.ao(channel)?;
        a.chan
            .ranges
            .get(a.chan.range as usize)
            .map(|(_, scale)| *scale)
            .ok_or(DeviceError::Unsupported {
                what: "a channel without that range",
            })
    }

    /// One `comedi_data_write`, at once.
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        AnalogOut::scale(self, channel)?.check_raw(channel, raw)?;
        let a = self.ao(channel)?;
        let c = &a.chan;
        // In 0..=maxdata (checked above), so it fits.
        let data = raw as u32;
        self.with_board(|b| {
            b.data_write(c.subdevice, c.channel, c.range, c.aref.raw(), data)?;
            // Under the board's lock: what a reopen writes back is what the board has.
            a.value
                .store(pack(data, c.range, c.aref.raw()), Ordering::Release);
            a.asked.store(true, Ordering::Release);
            Ok(())
        })
    }

    /// What was written, or what the board read back when the card opened it.
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let a = self.ao(channel)?;
        match unpack(a.value.load(Ordering::Acquire)) {
            Some((raw, _, _)) => Ok(i64::from(raw)),
            None if !self.is_online() => Err(DeviceError::Offline),
            None => Err(DeviceError::Stale { age: None }),
        }
    }
}

impl DigitalIn for ComediCard {
    fn input_count(&self) -> u32 {
        self.inputs.len()
    }

    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.inputs.check_bit(bit)?;
        if !self.is_online() {
            return Err(DeviceError::Offline);
        }
        if !self.fresh.load(Ordering::Acquire) {
            return Err(DeviceError::Stale { age: None });
        }
        self.inputs.get(bit)
    }
}

impl DigitalOut for ComediCard {
    fn output_count(&self) -> u32 {
        self.outputs.len()
    }

    /// One `comedi_dio_bitfield2`, at once.
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.outputs.check_bit(bit)?;
        self.write_bits(bit, bit, u64::from(value))
    }

    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.outputs.check_bit(bit)?;
        if !self.dout[bit as usize].known.load(Ordering::Acquire) {
            return Err(if self.is_online() {
                DeviceError::Stale { age: None }
            } else {
                DeviceError::Offline
            });
        }
        self.outputs.get(bit)
    }

    /// One `comedi_dio_bitfield2` per subdevice (and window of 32 channels) the span
    /// covers: bits of one subdevice change together.
    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = BitSpan::new(start, stop, self.output_count())?;
        span.check_value(value)?;
        self.write_bits(span.start(), span.stop(), value)
    }
}

impl EncoderHost for ComediCard {
    fn encoder_counter(&self, index: usize) -> &EncoderCounter {
        self.counters[index].1.counter()
    }

    fn check_encoder(&self, _index: usize) -> Result<(), DeviceError> {
        if self.is_online() {
            Ok(())
        } else {
            Err(DeviceError::Offline)
        }
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        Ok(())
    }
}
