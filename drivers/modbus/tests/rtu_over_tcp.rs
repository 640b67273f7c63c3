//! RTU frames over TCP, as serial device servers carry them: hwgw's client line
//! (`transport = "rtu_over_tcp"`) against pymodbus's TCP server with its RTU framer (a
//! Modbus implementation we did not write), on random register maps. Every point is read
//! exactly (integers to the count, floats to the bit) at the fewest requests the map's plan
//! allows, with no timeout, retry or bad reply.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{AnalogIn, Device, DeviceError, DigitalIn, Status};
use driver_modbus::codec::{ByteOrder, Layout, Number, ValueType, WordOrder};
use driver_modbus::line::{LineUnit, RtuOverTcp, Transport, UnitStats, UnitTiming};
use driver_modbus::plan::Table;
use driver_modbus::testing::TestLine;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;
use testkit::pymodbus::{PyModbus, pattern};
use testkit::rng::Rng;
use testkit::wait_until;

/// What a channel of the random map must read.
#[derive(Debug)]
enum Expect {
    /// An integer point: its raw value.
    Int(u32, i64),
    /// A float point: its value, bit for bit (None: NaN or infinite, the channel's status).
    Float(u32, Option<f64>),
    /// A bit (discrete input, read-only coil, or a register's bit).
    Bit(u32, bool),
}

/// The registers pymodbus holds at `address..address + n` of `table`.
fn registers(table: Table, address: u16, n: u16) -> Vec<u16> {
    (address..address + n)
        .map(|a| match table {
            Table::InputRegisters => pattern::input_register(a),
            _ => pattern::holding_register(a),
        })
        .collect()
}

/// A random map of 1 to 40 points over the pattern's addresses (no two on one address of a
/// table), as TOML, and what each channel must read.
fn random_map(rng: &mut Rng) -> (String, Vec<Expect>) {
    const TABLES: [Table; 4] = [
        Table::InputRegisters,
        Table::HoldingRegisters,
        Table::DiscreteInputs,
        Table::Coils,
    ];
    const TYPES: [ValueType; 7] = [
        ValueType::U16,
        ValueType::I16,
        ValueType::U32,
        ValueType::I32,
        ValueType::I64,
        ValueType::F32,
        ValueType::F64,
    ];
    let mut used: Vec<(Table, u16)> = Vec::new();
    let (mut toml, mut expect) = (String::new(), Vec::new());
    let (mut analog, mut bits) = (0u32, 0u32);
    let points = 1 + rng.below(40);
    // Addresses within a window, so reads coalesce and some span gaps.
    let window = [50u64, 400, 1990][rng.below(3) as usize];
    for _ in 0..points {
        let table = *rng.pick(&TABLES).unwrap();
        let address = rng.below(window) as u16;
        if table.is_bits() {
            if used.contains(&(table, address)) {
                continue;
            }
            used.push((table, address));
            let value = match table {
                Table::DiscreteInputs => pattern::discrete_input(address),
                _ => pattern::coil(address),
            };
            toml += &format!("[[point]]\ntable = \"{table}\"\naddress = {address}\n");
            if table == Table::Coils {
                toml += "read_only = true\n";
            }
            expect.push(Expect::Bit(bits, value));
            bits += 1;
            continue;
        }
        let bit_point = rng.below(5) == 0;
        let ty = if bit_point {
            ValueType::U16
        } else {
            *rng.pick(&TYPES).unwrap()
        };
        let n = ty.registers() as u16;
        if (0..n).any(|k| used.contains(&(table, address + k))) {
            continue;
        }
        used.extend((0..n).map(|k| (table, address + k)));
        let words = *rng
            .pick(&[WordOrder::HighFirst, WordOrder::LowFirst])
            .unwrap();
        let bytes = *rng.pick(&[ByteOrder::Normal, ByteOrder::Swapped]).unwrap();
        let regs = registers(table, address, n);
        toml += &format!("[[point]]\ntable = \"{table}\"\naddress = {address}\n");
        if table == Table::HoldingRegisters && !bit_point {
            toml += "read_only = true\n";
        }
        if bit_point {
            let bit = rng.below(16) as u8;
            toml += &format!("bit = {bit}\n");
            expect.push(Expect::Bit(bits, regs[0] >> bit & 1 == 1));
            bits += 1;
            continue;
        }
        toml += &format!(
            "type = \"{}\"\nwords = \"{}\"\nbytes = \"{}\"\n",
            serde_name(&ty),
            serde_name(&words),
            serde_name(&bytes)
        );
        let layout = Layout { ty, words, bytes };
        expect.push(match layout.decode(&regs).unwrap() {
            Number::Int(v) => Expect::Int(analog, v),
            // No u64 in the map: every u16 and u32 fits an i64.
            Number::UInt(v) => Expect::Int(analog, i64::try_from(v).unwrap()),
            Number::Float(v) => Expect::Float(analog, v.is_finite().then_some(v)),
        });
        analog += 1;
    }
    (toml, expect)
}

/// A config enum's name in TOML.
fn serde_name<T: std::fmt::Debug>(v: &T) -> String {
    let debug = format!("{v:?}");
    let mut out = String::new();
    for (i, c) in debug.chars().enumerate() {
        if c.is_ascii_uppercase() {
            if i > 0 {
                out.push('_');
            }
            out.push(c.to_ascii_lowercase());
        } else {
            out.push(c);
        }
    }
    out
}

#[test]
fn random_maps_read_exactly_over_rtu_frames_on_tcp_against_pymodbus() {
    let peer = PyModbus::start("pattern_rtu_over_tcp");
    let transport = Transport::RtuOverTcp(RtuOverTcp {
        addr: peer.addr,
        turnaround_us: 0,
    });
    let seed = std::env::var("HWGW_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0x5eed_0039);
    let mut rng = Rng::new(seed);
    for round in 0..12 {
        let (toml, expect) = random_map(&mut rng);
        if expect.is_empty() {
            continue;
        }
        let card = driver_modbus::testing::card(&toml, driver_modbus::map::ANY_GAP);
        let reads = card.map().reads().len() as u64;
        let stats = Arc::new(UnitStats::default());
        let timing = UnitTiming {
            unit: 1 + round as u8,
            poll: Duration::from_millis(20),
            timeout: Duration::from_secs(2),
            stale_after: 3,
            offline_after: 10,
            backoff_max: Duration::from_secs(2),
        };
        let line = TestLine::spawn(
            "rtu-tcp",
            transport.clone(),
            vec![LineUnit {
                card: card.clone(),
                timing,
                stats: stats.clone(),
            }],
        )
        .unwrap();
        let why = || format!("seed {seed:#x} round {round}:\n{toml}");
        wait_until("three good polls", || {
            stats.polls.load(Ordering::Relaxed) >= 3
        });
        drop(line);
        assert_eq!(card.health().status, Status::Online, "{}", why());
        for e in &expect {
            match *e {
                Expect::Int(ch, v) => {
                    assert_eq!(AnalogIn::read_raw(&*card, ch).unwrap(), v, "{}", why())
                }
                Expect::Float(ch, Some(v)) => assert_eq!(
                    AnalogIn::read(&*card, ch).unwrap().to_bits(),
                    v.to_bits(),
                    "{}",
                    why()
                ),
                Expect::Float(ch, None) => assert!(
                    matches!(
                        AnalogIn::read(&*card, ch),
                        Err(DeviceError::NotANumber { .. })
                    ),
                    "channel {ch}: {:?}\n{}",
                    AnalogIn::read(&*card, ch),
                    why()
                ),
                Expect::Bit(b, v) => assert_eq!(card.read_bit(b).unwrap(), v, "{}", why()),
            }
        }
        let load = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        let polls = load(&stats.polls);
        // Every request of every good poll: the plan's reads, no more (a poll under way
        // when the line stopped adds at most its reads).
        let requests = load(&stats.requests);
        assert!(
            (polls * reads..=(polls + 1) * reads).contains(&requests),
            "{requests} requests in {polls} polls of {reads} reads\n{}",
            why()
        );
        for (what, n) in [
            ("timeouts", load(&stats.timeouts)),
            ("bad replies", load(&stats.bad_replies)),
            ("transport errors", load(&stats.transport_errors)),
            ("exceptions", load(&stats.exceptions)),
        ] {
            assert_eq!(n, 0, "{what}\n{}", why());
        }
    }
}
