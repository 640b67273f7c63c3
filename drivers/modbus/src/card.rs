//! A Modbus unit as a card: the device side, between the register map and the poller.
//!
//! The device methods keep the real-time contract: they read the input image and update
//! the output image (atomics only). The poller — the card's bus activity — feeds each read's
//! reply to [`ModbusCard::apply_read`], reports each poll with
//! [`poll_succeeded`](ModbusCard::poll_succeeded) or [`poll_failed`](ModbusCard::poll_failed),
//! and sends what [`take_writes`](ModbusCard::take_writes) returns: changed outputs as
//! function codes 5/6 (one coil or register) or 15/16 (runs of consecutive addresses).
//!
//! # Delivery
//!
//! A write that returned `Ok` has been *taken* (stored in the output image), not yet
//! delivered: the poller carries it at the unit's next poll. Each output channel numbers
//! the writes it takes ([`DeliveryTracker`]); `take_writes` notes, per output, the number
//! its request carries, and the poller settles it: [`write_delivered`](ModbusCard::write_delivered)
//! when the unit answered the request, [`write_refused`](ModbusCard::write_refused) when it
//! answered with an exception (not sent again), and [`fail_pending`](ModbusCard::fail_pending)
//! when the unit went offline (or its line stopped) with writes on their way. A write that
//! fails in transit (timeout, broken connection) is sent again at the next poll and stays
//! pending until then. Whoever asked hears the outcome through
//! [`AnalogOut::delivery`] / [`DigitalOut::delivery`].

use crate::codec::Number;
use crate::map::{Map, Point, Role};
use crate::plan::{Read, Table};
use crate::value;
use arc_swap::ArcSwapOption;
use device_interface::bits::{BitImage, BitSpan};
use device_interface::time::{Clock, Timestamp};
use device_interface::{
    AnalogIn, AnalogOut, Delivery, DeliveryTracker, Device, DeviceError, DigitalIn, DigitalOut,
    Health, Scale, Status,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU8, AtomicU64, Ordering};

/// The data of one read's reply.
#[derive(Debug, Clone, Copy)]
pub enum ReadData<'a> {
    /// Registers (function codes 3 and 4), from the read's first address.
    Registers(&'a [u16]),
    /// Bits (function codes 1 and 2), from the read's first address.
    Bits(&'a [bool]),
}

/// A write to send.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Write {
    /// Function code 5.
    Coil {
        /// Address.
        address: u16,
        /// Value.
        value: bool,
    },
    /// Function code 15.
    Coils {
        /// First address.
        address: u16,
        /// Values from there.
        values: Vec<bool>,
    },
    /// Function code 6.
    Register {
        /// Address.
        address: u16,
        /// Value.
        value: u16,
    },
    /// Function code 16.
    Registers {
        /// First address.
        address: u16,
        /// Values from there.
        values: Vec<u16>,
    },
}

/// A reply that does not fit its request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ReplyError {
    /// No such read in the plan.
    #[error("read {0} is not in the plan")]
    NoSuchRead(usize),
    /// Registers for a bit read or bits for a register read.
    #[error("read {read}: the reply carries the wrong kind of data for {table}")]
    WrongKind {
        /// The read.
        read: usize,
        /// Its table.
        table: Table,
    },
    /// Fewer registers or bits than asked for.
    #[error("read {read}: {got} values in the reply, {expected} asked for")]
    Short {
        /// The read.
        read: usize,
        /// Asked for.
        expected: u16,
        /// Received.
        got: usize,
    },
    /// A counter register (an encoder) that decodes to no integer: the encoder keeps its
    /// count. (A float *analog* point holding NaN is that channel's status, not an error
    /// of the reply.)
    #[error("point {point}: the register holds {value}, not a number in range")]
    NotANumber {
        /// The point.
        point: usize,
        /// The value.
        value: f64,
    },
}

/// Where the writes to one kind of output stand, per channel.
struct Deliveries {
    /// Writes taken and settled.
    tracker: DeliveryTracker,
    /// The number of the newest write taken when [`ModbusCard::take_writes`] last took
    /// the output for sending: what its request carries.
    in_flight: Box<[AtomicU64]>,
    /// The newest write the unit answered (0: none).
    delivered: Box<[AtomicU64]>,
}

impl Deliveries {
    fn new(n: u32) -> Self {
        let numbers = || (0..n).map(|_| AtomicU64::new(0)).collect();
        Deliveries {
            tracker: DeliveryTracker::new(n),
            in_flight: numbers(),
            delivered: numbers(),
        }
    }

    fn count(&self) -> u32 {
        self.in_flight.len() as u32
    }

    /// `take_writes` took output `ch` for sending.
    fn sending(&self, ch: u32) {
        if let Some(f) = self.in_flight.get(ch as usize) {
            f.store(self.tracker.taken(ch), Ordering::Release);
        }
    }

    /// The request carrying output `ch` was answered.
    fn answered(&self, ch: u32) {
        if let (Some(f), Some(d)) = (
            self.in_flight.get(ch as usize),
            self.delivered.get(ch as usize),
        ) {
            let n = f.load(Ordering::Acquire);
            d.fetch_max(n, Ordering::AcqRel);
            self.tracker.delivered(ch, n);
        }
    }

    /// The request carrying output `ch` was refused, for `why`.
    fn refused(&self, ch: u32, why: &DeviceError) {
        if let Some(f) = self.in_flight.get(ch as usize) {
            self.tracker
                .failed(ch, f.load(Ordering::Acquire), why.clone());
        }
    }

    /// Output `ch`'s newest write failed and did not reach the unit since (a write failed
    /// as the unit went offline is still sent when it answers again): why.
    fn newest_failed(&self, ch: u32) -> Option<DeviceError> {
        let d = self.tracker.get(ch);
        let delivered = self
            .delivered
            .get(ch as usize)
            .map_or(0, |a| a.load(Ordering::Acquire));
        (d.failed > 0 && d.failed == d.taken && delivered < d.taken).then(|| {
            d.error.unwrap_or(DeviceError::Undelivered {
                reason: "no reason kept",
            })
        })
    }

    /// True while some output has a write taken and not yet settled.
    fn pending(&self) -> bool {
        (0..self.count()).any(|ch| {
            let d = self.tracker.get(ch);
            d.settled < d.taken
        })
    }
}

const ONLINE: u8 = 0;
const STALE: u8 = 1;
const OFFLINE: u8 = 2;

/// One Modbus unit's devices.
pub struct ModbusCard {
    map: Map,
    clock: Arc<dyn Clock>,
    ai: Box<[AtomicI64]>,
    ao: Box<[AtomicI64]>,
    ao_dirty: BitImage,
    di: BitImage,
    dout: BitImage,
    do_dirty: BitImage,
    /// Where the writes to the analog outputs stand.
    ao_delivery: Deliveries,
    /// Where the writes to the digital outputs stand.
    do_delivery: Deliveries,
    encoders: Box<[device_interface::encoder::WrappingCounter]>,
    status: AtomicU8,
    /// Time of the last good poll in ns plus one; 0: never.
    last_good: AtomicU64,
    last_error: ArcSwapOption<DeviceError>,
}

/// An encoder register's count (integer types; a float counter has none).
fn count_of(n: Number) -> Option<i64> {
    match n {
        Number::Int(v) => Some(v),
        Number::UInt(v) => Some(i64::try_from(v).unwrap_or(i64::MAX)),
        Number::Float(_) => None,
    }
}

impl ModbusCard {
    /// A card for `map`; offline until its first good poll (start-up never waits for the
    /// device).
    pub fn new(map: Map, clock: Arc<dyn Clock>) -> Arc<ModbusCard> {
        let [ai, ao, di, dout] = map.counts();
        // Analog images start at physical 0 (or the raw value nearest to it) until the
        // first reply.
        let image = |role: Role, n: u32| -> Box<[AtomicI64]> {
            (0..n)
                .map(|ch| AtomicI64::new(map.point(role, ch).map_or(0, value::initial_word)))
                .collect()
        };
        Arc::new(ModbusCard {
            ai: image(Role::AnalogIn, ai),
            ao: image(Role::AnalogOut, ao),
            ao_dirty: BitImage::new(ao),
            ao_delivery: Deliveries::new(ao),
            do_delivery: Deliveries::new(dout),
            encoders: map
                .points()
                .iter()
                .filter(|p| p.role == Role::Encoder)
                .filter_map(|p| {
                    let e = p.config.encoder?;
                    device_interface::encoder::WrappingCounter::new(
                        e.resolution,
                        e.upcounting,
                        16 * p.layout.ty.registers() as u32,
                    )
                    .ok()
                })
                .collect(),
            di: BitImage::new(di),
            dout: BitImage::new(dout),
            do_dirty: BitImage::new(dout),
            status: AtomicU8::new(OFFLINE),
            last_good: AtomicU64::new(0),
            last_error: ArcSwapOption::empty(),
            map,
            clock,
        })
    }

    /// The card's devices, for [`Registry::register_card`](device_interface::Registry::register_card)
    /// (only the interfaces its map has channels for).
    pub fn devices(self: &Arc<Self>) -> device_interface::CardDevices {
        let [ai, ao, di, dout] = self.map.counts();
        device_interface::CardDevices {
            analog_in: (ai > 0).then(|| self.clone() as Arc<dyn AnalogIn>),
            analog_out: (ao > 0).then(|| self.clone() as Arc<dyn AnalogOut>),
            digital_in: (di > 0).then(|| self.clone() as Arc<dyn DigitalIn>),
            digital_out: (dout > 0).then(|| self.clone() as Arc<dyn DigitalOut>),
            drives: Vec::new(),
            encoders: (0..self.encoders.len())
                .map(|index| {
                    let e: Arc<dyn device_interface::Encoder> =
                        Arc::new(ModbusEncoder::new(self.clone(), index));
                    (format!("encoder{index}"), e)
                })
                .collect(),
        }
    }

    /// True while some output change has not been taken for sending.
    pub fn writes_pending(&self) -> bool {
        let any = |img: &BitImage| (0..img.len()).any(|b| img.get(b).unwrap_or(false));
        any(&self.ao_dirty) || any(&self.do_dirty)
    }

    /// The register map.
    pub fn map(&self) -> &Map {
        &self.map
    }

    /// Decodes the reply to read `read` of the plan into the input image. A float point
    /// holding NaN or an infinity keeps it (its channel reads `NotANumber`); an encoder
    /// whose register holds no integer keeps its count, and the reply is reported bad —
    /// every other point is still taken.
    pub fn apply_read(&self, read: usize, data: ReadData<'_>) -> Result<(), ReplyError> {
        let r = self
            .map
            .reads()
            .get(read)
            .ok_or(ReplyError::NoSuchRead(read))?;
        self.apply(read, r, data)
    }

    /// As [`apply_read`](Self::apply_read), for a read of the unit's own plan (a read of
    /// the map's plan split where the unit has holes); `read` numbers it in errors.
    pub fn apply(&self, read: usize, r: &Read, data: ReadData<'_>) -> Result<(), ReplyError> {
        let got = match data {
            ReadData::Registers(regs) if !r.table.is_bits() => regs.len(),
            ReadData::Bits(bits) if r.table.is_bits() => bits.len(),
            _ => {
                return Err(ReplyError::WrongKind {
                    read,
                    table: r.table,
                });
            }
        };
        if got < usize::from(r.count) {
            return Err(ReplyError::Short {
                read,
                expected: r.count,
                got,
            });
        }
        let mut first_error = None;
        for &pi in &r.points {
            let p = &self.map.points()[pi];
            let offset = usize::from(p.span.address - r.start);
            match (data, p.role) {
                (ReadData::Bits(bits), Role::DigitalOut) => {
                    // Read back: the device's state, unless a change is still to be sent.
                    if !self.do_dirty.get(p.channel).unwrap_or(true) {
                        let _ = self.dout.set(p.channel, bits[offset]);
                    }
                }
                (ReadData::Bits(bits), _) => {
                    let _ = self.di.set(p.channel, bits[offset]);
                }
                (ReadData::Registers(regs), Role::DigitalIn) => {
                    let bit = p.config.bit.unwrap_or(0);
                    let _ = self.di.set(p.channel, regs[offset] >> bit & 1 == 1);
                }
                (ReadData::Registers(regs), Role::Encoder) => {
                    let raw = p.layout.decode(&regs[offset..]).ok().and_then(count_of);
                    match (raw, self.encoders.get(p.channel as usize)) {
                        (Some(raw), Some(e)) => e.sample(raw),
                        _ => {
                            first_error.get_or_insert(ReplyError::NotANumber {
                                point: pi,
                                value: f64::NAN,
                            });
                        }
                    }
                }
                (ReadData::Registers(regs), _) => {
                    // The reply length was checked, so decoding cannot come up short.
                    // A float holding NaN or an infinity is kept as it is: that channel
                    // reads NotANumber, the others are taken.
                    let decoded = p.layout.decode(&regs[offset..]);
                    let raw = decoded.as_ref().ok().and_then(|n| value::word_of(p, *n));
                    let value = decoded.map_or(f64::NAN, Number::as_f64);
                    let (image, dirty) = match p.role {
                        // Read back: the device's value, unless a change is still to be sent.
                        Role::AnalogOut => (&self.ao, self.ao_dirty.get(p.channel).unwrap_or(true)),
                        _ => (&self.ai, false),
                    };
                    match (raw, image.get(p.channel as usize)) {
                        (Some(raw), Some(cell)) if !dirty => cell.store(raw, Ordering::Release),
                        (Some(_), _) => {}
                        (None, _) => {
                            first_error.get_or_insert(ReplyError::NotANumber { point: pi, value });
                        }
                    }
                }
            }
        }
        first_error.map_or(Ok(()), Err)
    }

    /// True once a complete poll succeeded (every mapped input, and the outputs with
    /// `read_back`, hold the unit's values from then on).
    pub fn polled(&self) -> bool {
        self.last_good.load(Ordering::Acquire) != 0
    }

    /// Records a complete, good poll: the inputs are fresh and the unit online.
    pub fn poll_succeeded(&self) {
        self.last_good.store(
            self.clock.now().as_nanos().saturating_add(1),
            Ordering::Release,
        );
        self.status.store(ONLINE, Ordering::Release);
        self.last_error.store(None);
    }

    /// Records a failed poll: the error, and how bad the poller judges it — `Stale` or
    /// `Offline` lower the status; `Online` (a failure below the poller's thresholds) keeps
    /// whatever status the unit had. A failure never makes a unit more online than it was:
    /// a unit never seen stays offline.
    pub fn poll_failed(&self, error: DeviceError, status: Status) {
        self.last_error.store(Some(Arc::new(error)));
        let worse = match status {
            Status::Online => return,
            Status::Stale => STALE,
            Status::Offline => OFFLINE,
        };
        self.status.fetch_max(worse, Ordering::AcqRel);
    }

    /// The outputs written since the last call, as requests: runs of consecutive
    /// addresses become one function code 15 or 16 request, cut at the protocol's limits
    /// (1968 coils, 123 registers) between points, so a multi-register value goes out whole
    /// in one request.
    pub fn take_writes(&self) -> Vec<Write> {
        // (address, (word, first word of its point)).
        let mut regs: Vec<(u16, (u16, bool))> = Vec::new();
        let mut coils: Vec<(u16, (bool, bool))> = Vec::new();
        for p in self.map.points() {
            let dirty = match p.role {
                Role::AnalogOut => &self.ao_dirty,
                Role::DigitalOut => &self.do_dirty,
                Role::AnalogIn | Role::DigitalIn | Role::Encoder => continue,
            };
            // Clear first, then note the newest write's number, then read the value: a
            // write stores its value, takes its number and marks the output, in that order,
            // so the value sent is at least as new as the number noted, and a write after
            // the clear marks the output again.
            if !dirty.set(p.channel, false).unwrap_or(false) {
                continue;
            }
            self.delivery_of(p.role).sending(p.channel);
            if p.role == Role::DigitalOut {
                let on = self.dout.get(p.channel).unwrap_or(false);
                coils.push((p.span.address, (on, true)));
                continue;
            }
            let word = self.ao[p.channel as usize].load(Ordering::Acquire);
            // Writes were checked against the point's range, so encoding cannot fail; skip
            // rather than panic.
            if let Ok(words) = p.layout.encode(value::number(p, word)) {
                for (k, w) in words.as_slice().iter().enumerate() {
                    regs.push((p.span.address + k as u16, (*w, k == 0)));
                }
            }
        }
        let mut out = Vec::new();
        regs.sort_by_key(|r| r.0);
        for run in runs(&regs, usize::from(crate::pdu::MAX_WRITE_REGISTERS)) {
            out.push(match run {
                [(a, (v, _))] => Write::Register {
                    address: *a,
                    value: *v,
                },
                _ => Write::Registers {
                    address: run[0].0,
                    values: run.iter().map(|r| r.1.0).collect(),
                },
            });
        }
        coils.sort_by_key(|c| c.0);
        for run in runs(&coils, usize::from(crate::pdu::MAX_WRITE_COILS)) {
            out.push(match run {
                [(a, (v, _))] => Write::Coil {
                    address: *a,
                    value: *v,
                },
                _ => Write::Coils {
                    address: run[0].0,
                    values: run.iter().map(|c| c.1.0).collect(),
                },
            });
        }
        out
    }

    /// Marks the outputs `write` carried as changed again, so the next
    /// [`take_writes`](Self::take_writes) sends their current values (a write that failed
    /// in transit is retried, never dropped; its writers keep waiting).
    pub fn retry(&self, write: &Write) {
        self.each_output(write, |role, ch| {
            let _ = match role {
                Role::DigitalOut => self.do_dirty.set(ch, true),
                _ => self.ao_dirty.set(ch, true),
            };
        });
    }

    /// The unit answered `write` (a request [`take_writes`](Self::take_writes) returned):
    /// the writes it carried are delivered.
    pub fn write_delivered(&self, write: &Write) {
        self.each_output(write, |role, ch| self.delivery_of(role).answered(ch));
    }

    /// The unit refused `write` (an exception reply: sending it again would not help): the
    /// writes it carried failed, for `why`, and it is not sent again. Returns the number
    /// of outputs it carried.
    pub fn write_refused(&self, write: &Write, why: &DeviceError) -> usize {
        let mut n = 0;
        self.each_output(write, |role, ch| {
            self.delivery_of(role).refused(ch, why);
            n += 1;
        });
        n
    }

    /// Every write taken and not yet settled failed, for `why` (the unit went offline, or
    /// its line stopped): no writer waits for ever, and a write its writer was told failed
    /// is dropped — its changed mark cleared, so a unit that answers again never gets it
    /// later, when nobody asks for it any more. Returns the number of outputs that had
    /// writes pending.
    pub fn fail_pending(&self, why: &DeviceError) -> usize {
        let mut n = 0;
        for (d, dirty) in [
            (&self.ao_delivery, &self.ao_dirty),
            (&self.do_delivery, &self.do_dirty),
        ] {
            for ch in 0..d.count() {
                let state = d.tracker.get(ch);
                if state.settled >= state.taken {
                    continue;
                }
                // Number first, mark after: a write racing this takes a newer number and
                // its mark is set again below.
                let _ = dirty.set(ch, false);
                d.tracker.failed(ch, state.taken, why.clone());
                if d.tracker.taken(ch) > state.taken {
                    let _ = dirty.set(ch, true);
                }
                n += 1;
            }
        }
        n
    }

    /// The outputs whose newest write failed and has not reached the unit since
    /// (`(role, channel, why)`): the unit does not hold what was last written to them.
    pub fn failed_outputs(&self) -> Vec<(Role, u32, DeviceError)> {
        let mut out = Vec::new();
        for (role, d) in [
            (Role::AnalogOut, &self.ao_delivery),
            (Role::DigitalOut, &self.do_delivery),
        ] {
            for ch in 0..d.count() {
                if let Some(why) = d.newest_failed(ch) {
                    out.push((role, ch, why));
                }
            }
        }
        out
    }

    /// True while some output has a write taken and not yet settled (delivered or failed).
    pub fn deliveries_pending(&self) -> bool {
        self.ao_delivery.pending() || self.do_delivery.pending()
    }

    /// The deliveries of an output role (the digital outputs' for [`Role::DigitalOut`],
    /// the analog outputs' for any other).
    fn delivery_of(&self, role: Role) -> &Deliveries {
        match role {
            Role::DigitalOut => &self.do_delivery,
            _ => &self.ao_delivery,
        }
    }

    /// Calls `f(role, channel)` for each output `write` carries (a part of it is enough).
    fn each_output(&self, write: &Write, mut f: impl FnMut(Role, u32)) {
        let (coils, start, len) = match write {
            Write::Coil { address, .. } => (true, *address, 1),
            Write::Coils { address, values } => (true, *address, values.len()),
            Write::Register { address, .. } => (false, *address, 1),
            Write::Registers { address, values } => (false, *address, values.len()),
        };
        let end = u32::from(start) + len as u32;
        for p in self.map.points() {
            let (p_start, p_end) = (
                u32::from(p.span.address),
                u32::from(p.span.address) + u32::from(p.span.count),
            );
            if p_start >= end || p_end <= u32::from(start) {
                continue;
            }
            match (p.role, coils) {
                (Role::DigitalOut, true) | (Role::AnalogOut, false) => f(p.role, p.channel),
                _ => {}
            }
        }
    }

    fn check_input(&self) -> Result<(), DeviceError> {
        match self.status.load(Ordering::Acquire) {
            ONLINE => Ok(()),
            STALE => Err(DeviceError::Stale { age: self.age() }),
            // Why it is offline is in health().last_error.
            _ => Err(DeviceError::Offline),
        }
    }

    /// Stores an analog output's word, takes the write's number, marks the output: in
    /// that order (see [`take_writes`](Self::take_writes)). Atomics only.
    fn store_output(&self, channel: u32, word: i64) -> Result<(), DeviceError> {
        self.check_output()?;
        self.ao[channel as usize].store(word, Ordering::Release);
        self.ao_delivery.tracker.take(channel);
        self.ao_dirty.set(channel, true)?;
        Ok(())
    }

    fn check_output(&self) -> Result<(), DeviceError> {
        if self.status.load(Ordering::Acquire) == OFFLINE {
            return Err(DeviceError::Offline);
        }
        Ok(())
    }

    fn last_good(&self) -> Option<Timestamp> {
        match self.last_good.load(Ordering::Acquire) {
            0 => None,
            n => Some(Timestamp::from_nanos(n - 1)),
        }
    }

    fn age(&self) -> Option<std::time::Duration> {
        self.last_good().map(|t| self.clock.now().duration_since(t))
    }

    fn point(&self, role: Role, channel: u32, count: u32) -> Result<&Point, DeviceError> {
        self.map
            .point(role, channel)
            .ok_or(DeviceError::ChannelOutOfRange { channel, count })
    }
}

/// Splits sorted (address, (value, first of its point)) pairs into runs of consecutive
/// addresses of at most `max` items, each cut before the first item of a point (a point
/// is at most 4 registers, so a run always has a place to be cut).
fn runs<T>(items: &[(u16, (T, bool))], max: usize) -> Vec<&[(u16, (T, bool))]> {
    let mut out = Vec::new();
    let (mut start, mut cut_at) = (0, 0);
    for i in 0..items.len() {
        if i > start && u32::from(items[i].0) != u32::from(items[i - 1].0) + 1 {
            out.push(&items[start..i]);
            (start, cut_at) = (i, i);
        }
        if items[i].1.1 {
            cut_at = i;
        }
        if i + 1 - start > max {
            // Cut before the point under way (or here, if one point were longer than max).
            let cut = if cut_at > start { cut_at } else { i };
            out.push(&items[start..cut]);
            start = cut;
        }
    }
    if start < items.len() {
        out.push(&items[start..]);
    }
    out
}

impl Device for ModbusCard {
    fn health(&self) -> Health {
        Health {
            status: match self.status.load(Ordering::Acquire) {
                ONLINE => Status::Online,
                STALE => Status::Stale,
                _ => Status::Offline,
            },
            last_good: self.last_good(),
            checked_at: self.clock.now(),
            last_error: self.last_error.load().as_deref().cloned(),
        }
    }
}

impl AnalogIn for ModbusCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[0]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(self
            .point(Role::AnalogIn, channel, self.map.counts()[0])?
            .scale)
    }

    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let p = self.point(Role::AnalogIn, channel, self.map.counts()[0])?;
        self.check_input()?;
        value::raw(
            p,
            channel,
            self.ai[channel as usize].load(Ordering::Acquire),
        )
    }

    /// Exact for float registers (see [`value`]).
    fn read(&self, channel: u32) -> Result<f64, DeviceError> {
        let p = self.point(Role::AnalogIn, channel, self.map.counts()[0])?;
        self.check_input()?;
        value::physical(
            p,
            channel,
            self.ai[channel as usize].load(Ordering::Acquire),
        )
    }
}

impl AnalogOut for ModbusCard {
    fn channel_count(&self) -> u32 {
        self.map.counts()[1]
    }

    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        Ok(self
            .point(Role::AnalogOut, channel, self.map.counts()[1])?
            .scale)
    }

    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let p = self.point(Role::AnalogOut, channel, self.map.counts()[1])?;
        let word = value::word_for_raw(p, channel, raw)?;
        self.store_output(channel, word)
    }

    /// Exact for float registers (see [`value`]).
    fn write(&self, channel: u32, v: f64) -> Result<(), DeviceError> {
        let p = self.point(Role::AnalogOut, channel, self.map.counts()[1])?;
        let word = value::word_for_value(p, channel, v)?;
        self.store_output(channel, word)
    }

    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        let p = self.point(Role::AnalogOut, channel, self.map.counts()[1])?;
        value::raw(
            p,
            channel,
            self.ao[channel as usize].load(Ordering::Acquire),
        )
    }

    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        let p = self.point(Role::AnalogOut, channel, self.map.counts()[1])?;
        value::physical(
            p,
            channel,
            self.ao[channel as usize].load(Ordering::Acquire),
        )
    }

    /// The poller carries writes at the unit's next poll (see the module doc).
    fn delivery(&self, channel: u32) -> Option<Delivery> {
        Some(self.ao_delivery.tracker.get(channel))
    }
}

impl device_interface::bits::DigitalInputImage for ModbusCard {
    fn inputs(&self) -> &BitImage {
        &self.di
    }

    fn check_inputs(&self, _: BitSpan) -> Result<(), DeviceError> {
        self.check_input()
    }
}

impl device_interface::bits::DigitalOutputImage for ModbusCard {
    fn outputs(&self) -> &BitImage {
        &self.dout
    }

    fn check_outputs_writable(&self) -> Result<(), DeviceError> {
        self.check_output()
    }

    fn outputs_written(&self, written: device_interface::bits::Written) {
        use device_interface::bits::Written;
        // The values are in the image already: take the writes' numbers, then mark them
        // (see `take_writes`). The spans were checked against the same length: these
        // cannot fail.
        let _ = match written {
            Written::Bit { bit, .. } => {
                self.do_delivery.tracker.take(bit);
                self.do_dirty.set(bit, true).map(|_| ())
            }
            Written::Span { span, .. } => {
                for (bit, _) in span.bits() {
                    self.do_delivery.tracker.take(bit);
                }
                self.do_dirty.write_span(span, span.mask())
            }
        };
    }

    /// The poller carries writes at the unit's next poll (see the module doc).
    fn output_delivery(&self, bit: u32) -> Option<Delivery> {
        Some(self.do_delivery.tracker.get(bit))
    }
}

/// One counter-register encoder of a [`ModbusCard`], as a device of its own.
pub type ModbusEncoder = device_interface::encoder::CardEncoder<ModbusCard>;

impl device_interface::encoder::EncoderHost for ModbusCard {
    fn encoder_counter(&self, index: usize) -> &device_interface::encoder::EncoderCounter {
        self.encoders[index].counter()
    }

    fn check_encoder(&self, _: usize) -> Result<(), DeviceError> {
        self.check_input()
    }

    fn check_writable(&self) -> Result<(), DeviceError> {
        self.check_output()
    }
}
