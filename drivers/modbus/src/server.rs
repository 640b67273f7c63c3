//! hwgw as a Modbus TCP server: chosen devices of the registry as a register table, so a
//! SCADA system or `mbpoll` can read and write them.
//!
//! | table | device | read | write |
//! |---|---|---|---|
//! | input registers | AnalogIn / AnalogOut channel | `read` / `read_back` | — |
//! | holding registers | AnalogOut channel | `read_back` | `write` |
//! | discrete inputs | DigitalIn / DigitalOut bit | `read_bit` / `check_bit` | — |
//! | coils | DigitalOut bit | `check_bit` | `set_bit` |
//!
//! A register value is `(physical - offset) / scale` in the entry's type and layout.
//! Unmapped addresses (or a write that covers part of a multi-register value) answer
//! IllegalDataAddress; a value the device refuses answers IllegalDataValue; a device that
//! is offline or stale answers ServerDeviceFailure. The server is off unless configured and
//! listens only where it is told.
//!
//! # Writes a bus carries later
//!
//! A device whose bus carries a write after the call returned (a Modbus unit behind hwgw's
//! own client, another gateway's output: [`Delivery`]) has only *taken* it.
//! [`RegisterTable::answer`] checks and writes, and hands back the reply together with
//! those writes ([`Unsettled`]); the server sends the reply only once they are settled
//! (see [`listener`](crate::listener)):
//!
//! | the writes | answer |
//! |---|---|
//! | all delivered | the normal reply |
//! | one failed, its target offline ([`DeviceError::Offline`]) | 0x0B GatewayTargetDeviceFailedToRespond |
//! | one failed otherwise (refused by the unit, the bus stopped) | 0x04 ServerDeviceFailure |
//! | one still on its way after `write_confirm_ms` | 0x0B GatewayTargetDeviceFailedToRespond |
//!
//! The Modbus Application Protocol (v1.1b3, §7) gives 0x0B to a gateway that "obtained no
//! response from the target device", usually because it is not on the network: a unit
//! offline, or silent for as long as the master is kept waiting. 0x0A (gateway path
//! unavailable) means the gateway could not allocate a path to the target — misconfigured
//! or overloaded — which a configured table never meets at run time. A write that reached
//! its bus and was refused, or lost otherwise, is the server's device failing: 0x04.
//! Devices that apply a write within the call answer as soon as it returned.

use crate::codec::{Layout, Number, ValueType};
use crate::pdu::{Req, Resp, exception};
use crate::plan::Table;
use device_interface::{AnalogIn, AnalogOut, Delivery, DeviceError, DigitalIn, DigitalOut};
use std::sync::Arc;

/// An exception code ([`pdu::exception`](crate::pdu::exception)).
pub type ExceptionCode = u8;

/// Where an entry's value comes from (and goes to).
#[derive(Clone)]
pub enum Source {
    /// An analog input channel (read only).
    AnalogIn(Arc<dyn AnalogIn>, u32),
    /// An analog output channel (read back; written through holding registers).
    AnalogOut(Arc<dyn AnalogOut>, u32),
    /// A digital input bit (read only).
    DigitalIn(Arc<dyn DigitalIn>, u32),
    /// A digital output bit (read back; written through coils).
    DigitalOut(Arc<dyn DigitalOut>, u32),
}

/// One entry of the register table.
#[derive(Clone)]
pub struct Entry {
    /// The table.
    pub table: Table,
    /// First address.
    pub address: u16,
    /// Value type and layout (registers only).
    pub layout: Layout,
    /// Register value = (physical - offset) / scale.
    pub scale: f64,
    /// See `scale`.
    pub offset: f64,
    /// The device behind it.
    pub source: Source,
}

/// An output a request wrote to.
#[derive(Clone)]
enum Target {
    Analog(Arc<dyn AnalogOut>, u32),
    Digital(Arc<dyn DigitalOut>, u32),
}

impl Target {
    fn delivery(&self) -> Option<Delivery> {
        match self {
            Target::Analog(d, c) => d.delivery(*c),
            Target::Digital(d, b) => d.delivery(*b),
        }
    }
}

/// The writes a request made to devices whose bus carries them after the call returned
/// (see [`Delivery`]): each output and its write's number there. Its reply waits until
/// they are settled. Empty when every write was applied within its call.
#[derive(Clone, Default)]
pub struct Unsettled {
    writes: Vec<(Target, u64)>,
}

impl Unsettled {
    /// Notes the write just made to `target`, if its device tracks delivery.
    fn note(&mut self, target: Target) {
        if let Some(d) = target.delivery() {
            // The newest number: this write's, or a newer one's whose fate covers it.
            self.writes.push((target, d.taken));
        }
    }

    /// True when nothing waits (no write, or every device applied its write at once).
    pub fn is_empty(&self) -> bool {
        self.writes.is_empty()
    }

    /// How many writes are still on their way (as of the last [`check`](Self::check)).
    pub fn len(&self) -> usize {
        self.writes.len()
    }

    /// Where the writes stand now: `None` while one is on its way; `Some(Ok)` once every
    /// one is delivered; `Some(Err(why))` as soon as one failed. Writes found delivered
    /// are dropped, so each check asks only about those still on their way. Reads the
    /// devices' delivery state: not for real-time paths.
    pub fn check(&mut self) -> Option<Result<(), DeviceError>> {
        let mut failed = None;
        self.writes.retain(|(target, n)| {
            if failed.is_some() {
                return true;
            }
            // A device that stopped reporting delivery has nothing on its way.
            match target.delivery().map_or(Some(Ok(())), |d| d.outcome(*n)) {
                None => true,
                Some(Ok(())) => false,
                Some(Err(e)) => {
                    failed = Some(e);
                    false
                }
            }
        });
        match failed {
            Some(e) => Some(Err(e)),
            None => self.writes.is_empty().then_some(Ok(())),
        }
    }
}

/// The exception answering a write its device took and could not deliver, for `why`:
/// 0x0B GatewayTargetDeviceFailedToRespond when the target did not answer (offline), 0x04
/// ServerDeviceFailure otherwise (see the module doc).
pub fn undelivered(why: &DeviceError) -> ExceptionCode {
    match why {
        DeviceError::Offline => exception::GATEWAY_TARGET_FAILED_TO_RESPOND,
        _ => exception::SERVER_DEVICE_FAILURE,
    }
}

/// A checked request's reply, and the writes it must wait for before it is sent.
#[derive(Clone)]
pub struct Answer {
    /// The reply, once `unsettled` is delivered.
    pub reply: Resp,
    /// The writes on their way (empty for reads and for writes applied within the call).
    pub unsettled: Unsettled,
}

/// Why a table was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum TableError {
    /// Two entries on one address.
    #[error("entry {entry}: {table} {address} is already served by entry {other}")]
    Overlap {
        /// The later entry.
        entry: usize,
        /// The earlier one.
        other: usize,
        /// Table.
        table: Table,
        /// Address.
        address: u16,
    },
    /// A device in a table that cannot carry it.
    #[error("entry {entry}: {what}")]
    Mismatch {
        /// The entry.
        entry: usize,
        /// What does not fit.
        what: String,
    },
}

/// The register table the server serves.
#[derive(Clone)]
pub struct RegisterTable {
    entries: Vec<Entry>,
}

fn width(e: &Entry) -> u16 {
    if e.table.is_bits() {
        1
    } else {
        e.layout.ty.registers() as u16
    }
}

impl RegisterTable {
    /// Checks `entries`: each device fits its table, no two entries share an address.
    pub fn new(entries: Vec<Entry>) -> Result<RegisterTable, TableError> {
        for (i, e) in entries.iter().enumerate() {
            let ok = matches!(
                (e.table, &e.source),
                (
                    Table::InputRegisters,
                    Source::AnalogIn(..) | Source::AnalogOut(..)
                ) | (Table::HoldingRegisters, Source::AnalogOut(..))
                    | (
                        Table::DiscreteInputs,
                        Source::DigitalIn(..) | Source::DigitalOut(..)
                    )
                    | (Table::Coils, Source::DigitalOut(..))
            );
            if !ok {
                return Err(TableError::Mismatch {
                    entry: i,
                    what: format!(
                        "{} cannot serve this interface (see the table in the docs)",
                        e.table
                    ),
                });
            }
            let scale_ok = e.scale.is_finite() && e.scale != 0.0 && e.offset.is_finite();
            if !e.table.is_bits() && !scale_ok {
                return Err(TableError::Mismatch {
                    entry: i,
                    what: format!(
                        "scale {} and offset {}: expected a finite non-zero scale",
                        device_interface::text::Number(e.scale),
                        device_interface::text::Number(e.offset)
                    ),
                });
            }
            let (s, w) = (u32::from(e.address), u32::from(width(e)));
            if s + w > 65536 {
                return Err(TableError::Mismatch {
                    entry: i,
                    what: format!("addresses {s}..{} run past 65535", s + w),
                });
            }
            for (j, o) in entries[..i].iter().enumerate() {
                let (os, ow) = (u32::from(o.address), u32::from(width(o)));
                if o.table == e.table && s < os + ow && os < s + w {
                    return Err(TableError::Overlap {
                        entry: i,
                        other: j,
                        table: e.table,
                        address: e.address,
                    });
                }
            }
        }
        Ok(RegisterTable { entries })
    }

    fn find(&self, table: Table, address: u16) -> Option<&Entry> {
        self.entries.iter().find(|e| {
            e.table == table
                && e.address <= address
                && u32::from(address) < u32::from(e.address) + u32::from(width(e))
        })
    }

    fn read_registers(
        &self,
        table: Table,
        start: u16,
        count: u16,
    ) -> Result<Vec<u16>, ExceptionCode> {
        let mut out = Vec::with_capacity(usize::from(count));
        let end = u32::from(start) + u32::from(count);
        let mut a = u32::from(start);
        while a < end {
            let e = self
                .find(table, a as u16)
                .ok_or(exception::ILLEGAL_DATA_ADDRESS)?;
            let physical = match &e.source {
                Source::AnalogIn(d, c) => d.read(*c),
                Source::AnalogOut(d, c) => d.read_back(*c),
                _ => return Err(exception::ILLEGAL_DATA_ADDRESS),
            }
            .map_err(device_failure)?;
            let value = (physical - e.offset) / e.scale;
            let n = if e.layout.ty.is_float() {
                Number::Float(value)
            } else {
                Number::Int(value.round() as i64)
            };
            // A value the register type cannot hold saturates rather than lies.
            let regs = e
                .layout
                .encode(n)
                .or_else(|_| e.layout.encode(saturate(e.layout.ty, value)))
                .map_err(|_| exception::SERVER_DEVICE_FAILURE)?;
            for (k, r) in regs.as_slice().iter().enumerate() {
                let at = u32::from(e.address) + k as u32;
                if at >= u32::from(start) && at < end {
                    out.push(*r);
                }
            }
            a = u32::from(e.address) + u32::from(width(e));
        }
        Ok(out)
    }

    fn write_registers(&self, start: u16, values: &[u16]) -> Result<Unsettled, ExceptionCode> {
        let end = u32::from(start) + values.len() as u32;
        let mut a = u32::from(start);
        // Check first, write after: a refused part leaves every output as it was.
        let mut writes = Vec::new();
        while a < end {
            let e = self
                .find(Table::HoldingRegisters, a as u16)
                .ok_or(exception::ILLEGAL_DATA_ADDRESS)?;
            let w = u32::from(width(e));
            if u32::from(e.address) != a || a + w > end {
                return Err(exception::ILLEGAL_DATA_ADDRESS); // part of a multi-register value
            }
            let i = (a - u32::from(start)) as usize;
            let n = e
                .layout
                .decode(&values[i..i + w as usize])
                .map_err(|_| exception::ILLEGAL_DATA_VALUE)?;
            let Source::AnalogOut(d, c) = &e.source else {
                return Err(exception::ILLEGAL_DATA_ADDRESS);
            };
            writes.push((d.clone(), *c, n.as_f64() * e.scale + e.offset));
            a += w;
        }
        let mut unsettled = Unsettled::default();
        for (d, c, v) in writes {
            d.write(c, v).map_err(|err| match err {
                DeviceError::ValueOutOfRange { .. } | DeviceError::RawOutOfRange { .. } => {
                    exception::ILLEGAL_DATA_VALUE
                }
                other => device_failure(other),
            })?;
            unsettled.note(Target::Analog(d, c));
        }
        Ok(unsettled)
    }

    fn read_bits(&self, table: Table, start: u16, count: u16) -> Result<Vec<bool>, ExceptionCode> {
        (u32::from(start)..u32::from(start) + u32::from(count))
            .map(|a| {
                let e = self
                    .find(table, a as u16)
                    .ok_or(exception::ILLEGAL_DATA_ADDRESS)?;
                match &e.source {
                    Source::DigitalIn(d, b) => d.read_bit(*b),
                    Source::DigitalOut(d, b) => d.check_bit(*b),
                    _ => return Err(exception::ILLEGAL_DATA_ADDRESS),
                }
                .map_err(device_failure)
            })
            .collect()
    }

    fn write_coils(&self, start: u16, values: &[bool]) -> Result<Unsettled, ExceptionCode> {
        let mut targets = Vec::new();
        for (i, v) in values.iter().enumerate() {
            let a = u32::from(start) + i as u32;
            let e = self
                .find(Table::Coils, a as u16)
                .ok_or(exception::ILLEGAL_DATA_ADDRESS)?;
            let Source::DigitalOut(d, b) = &e.source else {
                return Err(exception::ILLEGAL_DATA_ADDRESS);
            };
            targets.push((d.clone(), *b, *v));
        }
        let mut unsettled = Unsettled::default();
        for (d, b, v) in targets {
            d.set_bit(b, v).map_err(device_failure)?;
            unsettled.note(Target::Digital(d, b));
        }
        Ok(unsettled)
    }

    /// Answers one checked request ([`pdu::parse`](crate::pdu::parse)): the reply and the
    /// writes it waits for, or an exception code. A write is made here; its reply is due
    /// only once [`Answer::unsettled`] is delivered (the server waits in its connection's
    /// task, see [`listener`](crate::listener)).
    pub fn answer(&self, req: Req) -> Result<Answer, ExceptionCode> {
        let mut unsettled = Unsettled::default();
        let reply = match req {
            Req::ReadRegisters {
                function,
                start,
                count,
            } => {
                let table = if function == 4 {
                    Table::InputRegisters
                } else {
                    Table::HoldingRegisters
                };
                Resp::Registers(function, self.read_registers(table, start, count)?)
            }
            Req::ReadBits {
                function,
                start,
                count,
            } => {
                let table = if function == 2 {
                    Table::DiscreteInputs
                } else {
                    Table::Coils
                };
                Resp::Bits(function, self.read_bits(table, start, count)?)
            }
            Req::WriteRegister { address, value } => {
                unsettled = self.write_registers(address, &[value])?;
                Resp::Echo(6, address, value)
            }
            Req::WriteRegisters { start, values } => {
                unsettled = self.write_registers(start, &values)?;
                Resp::Written(16, start, values.len() as u16)
            }
            Req::WriteCoil { address, on } => {
                unsettled = self.write_coils(address, &[on])?;
                Resp::Echo(5, address, if on { 0xFF00 } else { 0 })
            }
            Req::WriteCoils { start, values } => {
                unsettled = self.write_coils(start, &values)?;
                Resp::Written(15, start, values.len() as u16)
            }
        };
        Ok(Answer { reply, unsettled })
    }
}

fn device_failure(_: DeviceError) -> ExceptionCode {
    exception::SERVER_DEVICE_FAILURE
}

fn saturate(ty: ValueType, v: f64) -> Number {
    let (min, max): (i128, i128) = match ty {
        ValueType::U16 => (0, i128::from(u16::MAX)),
        ValueType::I16 => (i128::from(i16::MIN), i128::from(i16::MAX)),
        ValueType::U32 => (0, i128::from(u32::MAX)),
        ValueType::I32 => (i128::from(i32::MIN), i128::from(i32::MAX)),
        ValueType::U64 => (0, i128::from(i64::MAX)),
        ValueType::I64 => (i128::from(i64::MIN), i128::from(i64::MAX)),
        ValueType::F32 | ValueType::F64 => return Number::Float(v),
    };
    let r = if v.is_nan() {
        0
    } else {
        (v.round() as i128).clamp(min, max)
    };
    Number::Int(r as i64)
}
