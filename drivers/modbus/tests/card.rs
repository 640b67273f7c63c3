//! The Modbus card's device side against the conformance kit, with a simulated register
//! memory standing in for the unit: replies decoded into the image, writes coalesced.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::conformance;
use device_interface::time::{SimClock, Timestamp};
use device_interface::{AnalogIn, AnalogOut, Device, DeviceError, DigitalIn, DigitalOut, Status};
use driver_modbus::card::{ModbusCard, ReadData, ReplyError, Write};
use driver_modbus::codec::Number;
use driver_modbus::map::{Map, PointConfig, Role};
use std::cell::RefCell;
use std::sync::Arc;
use std::time::Duration;

const MAP: &str = r#"
[[point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1
unit = "degC"
[[point]]
table = "input_registers"
address = 1
type = "u32"
words = "low_first"
[[point]]
table = "input_registers"
address = 3
type = "f32"
bytes = "swapped"
unit = "bar"
[[point]]
table = "holding_registers"
address = 100
type = "i32"
read_only = true
[[point]]
table = "holding_registers"
address = 10
scale = 0.01
unit = "V"
[[point]]
table = "holding_registers"
address = 11
type = "f32"
[[point]]
table = "holding_registers"
address = 20
type = "i16"
[[point]]
table = "discrete_inputs"
address = 0
[[point]]
table = "discrete_inputs"
address = 1
[[point]]
table = "input_registers"
address = 40
bit = 0
[[point]]
table = "input_registers"
address = 40
bit = 15
[[point]]
table = "coils"
address = 0
[[point]]
table = "coils"
address = 1
[[point]]
table = "coils"
address = 7
[[point]]
table = "input_registers"
address = 50
type = "u16"
encoder = { resolution = 1000 }
[[point]]
table = "holding_registers"
address = 60
type = "i32"
read_only = true
encoder = { resolution = -360, upcounting = false }
"#;

fn map() -> Map {
    let t: toml::Table = toml::from_str(MAP).unwrap();
    let points: Vec<PointConfig> = t["point"].clone().try_into().unwrap();
    Map::new(&points, 4).unwrap()
}

/// The unit's memory: what a poll would read.
struct Unit {
    registers: [Vec<u16>; 2], // input, holding
    bits: Vec<bool>,          // discrete inputs
}

impl Unit {
    fn new() -> Self {
        Unit {
            registers: [vec![0; 256], vec![0; 256]],
            bits: vec![false; 64],
        }
    }

    /// One complete poll of `card` against this memory.
    fn poll(&self, card: &ModbusCard) {
        use driver_modbus::plan::Table;
        for (i, r) in card.map().reads().iter().enumerate() {
            let (s, e) = (
                usize::from(r.start),
                usize::from(r.start) + usize::from(r.count),
            );
            let data = match r.table {
                Table::InputRegisters => ReadData::Registers(&self.registers[0][s..e]),
                Table::HoldingRegisters => ReadData::Registers(&self.registers[1][s..e]),
                _ => ReadData::Bits(&self.bits[s..e]),
            };
            card.apply_read(i, data).unwrap();
        }
        card.poll_succeeded();
    }
}

fn card() -> Arc<ModbusCard> {
    ModbusCard::new(
        map(),
        Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000_000))),
    )
}

#[test]
fn conformance_every_rule() {
    let card = card();
    let unit = RefCell::new(Unit::new());
    unit.borrow().poll(&card);
    let map = map();
    let mut set_ai = |ch: u32, raw: i64| {
        let p = map.point(Role::AnalogIn, ch).unwrap();
        let n = if p.layout.ty.is_float() {
            Number::Float(raw as f64 * p.step)
        } else if raw < 0 {
            Number::Int(raw)
        } else {
            Number::UInt(raw as u64)
        };
        let regs = p.layout.encode(n).unwrap();
        let table = if p.config.table == driver_modbus::plan::Table::InputRegisters {
            0
        } else {
            1
        };
        let a = usize::from(p.config.address);
        unit.borrow_mut().registers[table][a..a + regs.as_slice().len()]
            .copy_from_slice(regs.as_slice());
        unit.borrow().poll(&card);
    };
    conformance::check_analog_in(&*card, Some(&mut set_ai)).assert_complete();
    let mut set_di = |bit: u32, v: bool| {
        let p = map.point(Role::DigitalIn, bit).unwrap();
        let a = usize::from(p.config.address);
        let mut u = unit.borrow_mut();
        match p.config.bit {
            None => u.bits[a] = v,
            Some(b) => {
                let reg = &mut u.registers[0][a];
                *reg = if v { *reg | 1 << b } else { *reg & !(1 << b) };
            }
        }
        drop(u);
        unit.borrow().poll(&card);
    };
    conformance::check_digital_in(&*card, Some(&mut set_di)).assert_complete();
    conformance::check_analog_out(&*card).assert_complete();
    conformance::check_digital_out(&*card).assert_complete();

    // Encoders from counter registers: motion is the counter counting, across its wrap.
    let devices = card.devices();
    assert_eq!(devices.encoders.len(), 2);
    for (i, (name, enc)) in devices.encoders.iter().enumerate() {
        assert_eq!(name, &format!("encoder{i}"));
        let p = map
            .points()
            .iter()
            .filter(|p| p.role == Role::Encoder)
            .nth(i)
            .unwrap();
        let (table, a) = (
            if p.config.table == driver_modbus::plan::Table::InputRegisters {
                0
            } else {
                1
            },
            usize::from(p.config.address),
        );
        let mut motion = |n: i64| {
            let mut u = unit.borrow_mut();
            let regs = &mut u.registers[table];
            if p.layout.ty.registers() == 1 {
                regs[a] = (i64::from(regs[a]) + n).rem_euclid(1 << 16) as u16;
            } else {
                let v = ((u32::from(regs[a]) << 16) | u32::from(regs[a + 1])) as i64 + n;
                let v = v.rem_euclid(1 << 32) as u32;
                regs[a] = (v >> 16) as u16;
                regs[a + 1] = v as u16;
            }
            drop(u);
            unit.borrow().poll(&card);
        };
        conformance::check_encoder(&**enc, Some(&mut motion)).assert_complete();
    }
}

#[test]
fn a_counter_encoder_counts_turns_across_the_register_wrap() {
    let card = card();
    let mut unit = Unit::new();
    unit.registers[0][50] = 65_000;
    unit.poll(&card); // baseline
    let enc = card.devices().encoders.remove(0).1;
    assert_eq!((enc.position().unwrap(), enc.turn().unwrap()), (0, 0));
    unit.registers[0][50] = 700; // +1236 counts across the 16-bit wrap
    unit.poll(&card);
    assert_eq!((enc.position().unwrap(), enc.turn().unwrap()), (236, 1));
    unit.registers[0][50] = 64_000; // -2236 counts back across the wrap
    unit.poll(&card);
    assert_eq!((enc.position().unwrap(), enc.turn().unwrap()), (0, -1));
}

#[test]
fn replies_decode_every_layout_into_physical_values() {
    let card = card();
    let mut unit = Unit::new();
    unit.registers[0][0] = (-215i16) as u16; // -21.5 degC
    unit.registers[0][1] = 0x0001; // u32 low word first: 0x0002_0001
    unit.registers[0][2] = 0x0002;
    let f = 2.5f32.to_bits();
    unit.registers[0][3] = ((f >> 16) as u16).swap_bytes();
    unit.registers[0][4] = (f as u16).swap_bytes();
    unit.registers[1][100] = 0xFFFF; // i32 -2
    unit.registers[1][101] = 0xFFFE;
    unit.bits[1] = true;
    unit.registers[0][40] = 0x8000; // bit 15 on, bit 0 off
    unit.poll(&card);
    assert_eq!(card.read(0).unwrap(), -21.5);
    assert_eq!(card.read_raw(1).unwrap(), 0x0002_0001);
    assert_eq!(card.read(2).unwrap(), 2.5);
    assert_eq!(AnalogIn::range(&*card, 2).unwrap().unit.as_str(), "bar");
    assert_eq!(card.read(3).unwrap(), -2.0);
    assert_eq!(card.read_sequence(0, 3).unwrap(), 0b1010);
}

/// A float setpoint takes any finite value its register holds, far past the 0.001 grid
/// of old (±8388.608 for an f32), and exactly; beyond the type's range it is refused.
#[test]
fn float_outputs_take_the_types_whole_range_exactly() {
    let card = card();
    Unit::new().poll(&card);
    let _ = card.take_writes();
    for v in [12345.678f32, 1.0e6, -3.25e9, 0.0004, 1.0e30] {
        card.write(1, f64::from(v)).unwrap();
        assert_eq!(card.read_back(1).unwrap(), f64::from(v));
        let f = v.to_bits();
        assert_eq!(
            card.take_writes(),
            vec![Write::Registers {
                address: 11,
                values: vec![(f >> 16) as u16, f as u16]
            }],
            "{v} sent as its f32"
        );
    }
    assert!(matches!(
        card.write(1, 1.0e39),
        Err(DeviceError::ValueOutOfRange { channel: 1, .. })
    ));
    assert_eq!(
        card.read_back(1).unwrap(),
        f64::from(1.0e30f32),
        "a refusal keeps the value"
    );
}

/// 64 f32 setpoints (128 registers) and 2000 coils in a row: each request within the
/// protocol's limits (123 registers, 1968 coils), no value cut between two requests.
#[test]
fn write_runs_are_cut_at_the_protocols_limits_between_points() {
    let mut map = String::new();
    for i in 0..64 {
        map += &format!(
            "[[point]]\ntable = \"holding_registers\"\naddress = {}\ntype = \"f32\"\n",
            1000 + 2 * i
        );
    }
    for i in 0..2000 {
        map += &format!("[[point]]\ntable = \"coils\"\naddress = {i}\n");
    }
    let card = driver_modbus::testing::card(&map, 0);
    card.poll_succeeded();
    for ch in 0..64 {
        card.write(ch, f64::from(ch) + 0.5).unwrap();
    }
    for bit in 0..2000 {
        card.set_bit(bit, bit % 3 == 0).unwrap();
    }
    let writes = card.take_writes();
    let mut words = Vec::new();
    let mut bits = Vec::new();
    for w in &writes {
        match w {
            Write::Registers { address, values } => {
                assert!(
                    values.len() <= 123,
                    "{} registers in one FC16",
                    values.len()
                );
                assert_eq!(
                    usize::from(*address),
                    1000 + words.len(),
                    "in order, no hole"
                );
                assert_eq!(values.len() % 2, 0, "an f32 cut in two at {address}");
                words.extend_from_slice(values);
            }
            Write::Coils { address, values } => {
                assert!(values.len() <= 1968, "{} coils in one FC15", values.len());
                assert_eq!(usize::from(*address), bits.len());
                bits.extend_from_slice(values);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(writes.len(), 4, "{writes:?}");
    let floats: Vec<f32> = words
        .chunks(2)
        .map(|w| f32::from_bits(u32::from(w[0]) << 16 | u32::from(w[1])))
        .collect();
    assert_eq!(floats, (0..64).map(|c| c as f32 + 0.5).collect::<Vec<_>>());
    assert_eq!(bits, (0..2000).map(|b| b % 3 == 0).collect::<Vec<_>>());
}

#[test]
fn output_writes_become_coalesced_requests() {
    let card = card();
    assert!(
        matches!(card.write(0, 1.0), Err(DeviceError::Offline)),
        "no writes before the unit answered"
    );
    Unit::new().poll(&card);
    assert!(card.take_writes().is_empty());
    card.write(0, 2.5).unwrap(); // holding 10, scale 0.01 -> 250
    card.write(1, 1.5).unwrap(); // holding 11..=12, f32
    card.write(2, -3.0).unwrap(); // holding 20, i16
    card.set_bit(0, true).unwrap(); // coil 0
    card.set_bit(1, true).unwrap(); // coil 1
    card.set_bit(2, true).unwrap(); // coil 7
    let f = 1.5f32.to_bits();
    assert_eq!(
        card.take_writes(),
        vec![
            Write::Registers {
                address: 10,
                values: vec![250, (f >> 16) as u16, f as u16]
            },
            Write::Register {
                address: 20,
                value: (-3i16) as u16
            },
            Write::Coils {
                address: 0,
                values: vec![true, true]
            },
            Write::Coil {
                address: 7,
                value: true
            },
        ]
    );
    assert!(card.take_writes().is_empty(), "each change is sent once");
    card.set_bit(0, false).unwrap();
    assert_eq!(
        card.take_writes(),
        vec![Write::Coil {
            address: 0,
            value: false
        }]
    );
    assert!(
        card.write(0, 1e9).is_err(),
        "u16 * 0.01 tops out at 655.35 V"
    );
}

#[test]
fn bad_replies_are_refused_and_counted_by_the_caller() {
    let card = card();
    assert_eq!(
        card.apply_read(99, ReadData::Bits(&[])).unwrap_err(),
        ReplyError::NoSuchRead(99)
    );
    let regs_read = card
        .map()
        .reads()
        .iter()
        .position(|r| !r.table.is_bits())
        .unwrap();
    assert!(matches!(
        card.apply_read(regs_read, ReadData::Bits(&[true])),
        Err(ReplyError::WrongKind { .. })
    ));
    assert!(matches!(
        card.apply_read(regs_read, ReadData::Registers(&[1])),
        Err(ReplyError::Short { .. })
    ));
    // A NaN float is that channel's status; the others in the reply are taken and the
    // reply is good.
    let mut unit = Unit::new();
    unit.registers[0][0] = 7;
    let nan = f32::NAN.to_bits();
    unit.registers[0][3] = ((nan >> 16) as u16).swap_bytes();
    unit.registers[0][4] = (nan as u16).swap_bytes();
    let r = card
        .map()
        .reads()
        .iter()
        .position(|r| r.table == driver_modbus::plan::Table::InputRegisters && r.start == 0)
        .unwrap();
    card.apply_read(
        r,
        ReadData::Registers(&unit.registers[0][..usize::from(card.map().reads()[r].count)]),
    )
    .unwrap();
    card.poll_succeeded();
    assert_eq!(card.read_raw(0).unwrap(), 7);
    let e = card.read(2).unwrap_err();
    assert!(
        matches!(
            e,
            DeviceError::NotANumber {
                channel: 2,
                what: "NaN"
            }
        ),
        "{e}"
    );
    assert_eq!(e.to_string(), "channel 2 holds NaN, not a number");
    assert!(matches!(
        card.read_raw(2),
        Err(DeviceError::NotANumber { .. })
    ));
    assert_eq!(card.health().status, Status::Online);
}

#[test]
fn health_follows_the_poller() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(5_000_000_000)));
    let card = ModbusCard::new(map(), clock.clone());
    assert_eq!(card.health().status, Status::Offline);
    assert!(
        matches!(card.read(0), Err(DeviceError::Offline)),
        "never seen: offline, not a made-up value"
    );
    Unit::new().poll(&card);
    assert_eq!(card.health().status, Status::Online);
    clock.advance(Duration::from_millis(300));
    card.poll_failed(
        DeviceError::bus(std::io::Error::from(std::io::ErrorKind::TimedOut)),
        Status::Stale,
    );
    assert!(
        matches!(card.read(0), Err(DeviceError::Stale { age: Some(a) }) if a == Duration::from_millis(300))
    );
    card.write(0, 1.0).expect("a stale unit still takes writes");
    card.poll_failed(DeviceError::Offline, Status::Online);
    assert_eq!(
        card.health().status,
        Status::Stale,
        "a minor failure does not hide staleness"
    );
    card.poll_failed(DeviceError::Offline, Status::Offline);
    let h = card.health();
    assert_eq!(
        (h.status, h.age()),
        (Status::Offline, Some(Duration::from_millis(300)))
    );
    assert!(card.write(0, 1.0).is_err());
}

#[test]
fn read_back_shows_the_device_but_a_pending_write_wins() {
    let t: toml::Table = toml::from_str("[[point]]\ntable = \"holding_registers\"\naddress = 0\n[[point]]\ntable = \"coils\"\naddress = 0\n").unwrap();
    let points: Vec<PointConfig> = t["point"].clone().try_into().unwrap();
    let card = ModbusCard::new(
        Map::with_read_back(&points, 0, true).unwrap(),
        Arc::new(SimClock::new(Timestamp::ZERO)),
    );
    let reads = card.map().reads().to_vec();
    assert_eq!(reads.len(), 2, "outputs are polled with read_back");
    let coils = reads
        .iter()
        .position(|r| r.table == driver_modbus::plan::Table::Coils)
        .unwrap();
    let regs = 1 - coils;
    // The device holds 7 and coil on: read back shows it.
    card.apply_read(regs, ReadData::Registers(&[7])).unwrap();
    card.apply_read(coils, ReadData::Bits(&[true])).unwrap();
    card.poll_succeeded();
    assert_eq!(AnalogOut::read_back_raw(&*card, 0).unwrap(), 7);
    assert!(card.check_bit(0).unwrap());
    // A write not yet sent is not overwritten by the device's old value...
    card.write_raw(0, 9).unwrap();
    card.set_bit(0, false).unwrap();
    card.apply_read(regs, ReadData::Registers(&[7])).unwrap();
    card.apply_read(coils, ReadData::Bits(&[true])).unwrap();
    assert_eq!(AnalogOut::read_back_raw(&*card, 0).unwrap(), 9);
    assert!(!card.check_bit(0).unwrap());
    // ...and once sent, the device's value is shown again.
    assert_eq!(card.take_writes().len(), 2);
    card.apply_read(regs, ReadData::Registers(&[9])).unwrap();
    assert_eq!(AnalogOut::read_back_raw(&*card, 0).unwrap(), 9);
}

/// The outcome of write `n` to analog output `ch` (None: on its way).
fn analog_outcome(card: &ModbusCard, ch: u32, n: u64) -> Option<Result<(), DeviceError>> {
    AnalogOut::delivery(card, ch).unwrap().outcome(n)
}

/// The outcome of write `n` to digital output `bit` (None: on its way).
fn digital_outcome(card: &ModbusCard, bit: u32, n: u64) -> Option<Result<(), DeviceError>> {
    DigitalOut::delivery(card, bit).unwrap().outcome(n)
}

/// Each write is numbered when taken, and settled by the request that carried it: a write
/// made after `take_writes` stays on its way until a request carries it in turn.
#[test]
fn deliveries_are_settled_by_the_request_that_carried_them() {
    let card = card();
    Unit::new().poll(&card);
    assert!(card.take_writes().is_empty());
    card.write(0, 2.5).unwrap(); // holding 10
    let a = AnalogOut::delivery(&*card, 0).unwrap().taken;
    card.set_sequence(0, 1, 0b11).unwrap(); // coils 0 and 1
    let (b0, b1) = (
        DigitalOut::delivery(&*card, 0).unwrap().taken,
        DigitalOut::delivery(&*card, 1).unwrap().taken,
    );
    assert_eq!((a, b0, b1), (1, 1, 1), "each output numbers its own writes");
    assert!(
        analog_outcome(&card, 0, a).is_none(),
        "taken, not delivered"
    );
    let writes = card.take_writes();
    assert!(card.deliveries_pending());
    // A newer value after the requests were made: not carried by them.
    card.write(0, 3.0).unwrap();
    let a2 = AnalogOut::delivery(&*card, 0).unwrap().taken;
    for w in &writes {
        card.write_delivered(w);
    }
    assert!(matches!(analog_outcome(&card, 0, a), Some(Ok(()))));
    assert!(matches!(digital_outcome(&card, 0, b0), Some(Ok(()))));
    assert!(matches!(digital_outcome(&card, 1, b1), Some(Ok(()))));
    assert!(
        analog_outcome(&card, 0, a2).is_none(),
        "the newer value is still on its way"
    );
    // The unit refuses the request carrying it: failed, with the reason, and not sent
    // again.
    let writes = card.take_writes();
    assert_eq!(
        writes,
        vec![Write::Register {
            address: 10,
            value: 300
        }]
    );
    let why = DeviceError::Undelivered { reason: "refused" };
    assert_eq!(card.write_refused(&writes[0], &why), 1);
    assert!(matches!(
        analog_outcome(&card, 0, a2),
        Some(Err(DeviceError::Undelivered { reason: "refused" }))
    ));
    assert!(
        card.take_writes().is_empty(),
        "a refused write is not resent"
    );
    assert_eq!(card.failed_outputs().len(), 1);
    // A write lost in transit is retried and stays on its way; the unit going offline
    // fails it, and it is dropped: never sent should the unit answer again (its writer was
    // told it failed).
    card.set_bit(2, true).unwrap(); // coil 7
    let c = DigitalOut::delivery(&*card, 2).unwrap().taken;
    let writes = card.take_writes();
    card.retry(&writes[0]);
    assert!(digital_outcome(&card, 2, c).is_none());
    assert_eq!(card.fail_pending(&DeviceError::Offline), 1);
    assert!(matches!(
        digital_outcome(&card, 2, c),
        Some(Err(DeviceError::Offline))
    ));
    assert!(!card.deliveries_pending());
    assert_eq!(card.failed_outputs().len(), 2);
    assert!(
        card.take_writes().is_empty(),
        "a failed write is not sent later"
    );
    assert_eq!(card.fail_pending(&DeviceError::Offline), 0, "nothing left");
    // A newer write after the failure goes out as usual.
    card.set_bit(2, false).unwrap();
    let d = DigitalOut::delivery(&*card, 2).unwrap().taken;
    let again = card.take_writes();
    assert_eq!(again.len(), 1);
    card.write_delivered(&again[0]);
    assert!(matches!(digital_outcome(&card, 2, d), Some(Ok(()))));
    let failed: Vec<(Role, u32)> = card
        .failed_outputs()
        .into_iter()
        .map(|(role, ch, _)| (role, ch))
        .collect();
    assert_eq!(failed, vec![(Role::AnalogOut, 0)]);
    // A write refused before it is taken has no number.
    card.poll_failed(DeviceError::Offline, Status::Offline);
    assert!(card.write(0, 1.0).is_err());
    assert_eq!(AnalogOut::delivery(&*card, 0).unwrap().taken, a2);
}
