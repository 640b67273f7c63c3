//! The server's request path (the checks of `pdu`, the register table's answer, the reply's
//! encoding) under a seeded storm of random and mutated request PDUs: no panic, every reply
//! well formed, the exceptions the specification gives. Over the same devices a Modbus
//! card offers (a card built from the shared fixture map, online).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{
    AnalogIn, AnalogOut, Delivery, Device, DeviceError, DigitalIn, DigitalOut, Health, Scale,
};
use driver_modbus::card::ModbusCard;
use driver_modbus::codec::{ByteOrder, Layout, ValueType, WordOrder};
use driver_modbus::pdu::{self, Refusal};
use driver_modbus::plan::Table;
use driver_modbus::server::{Entry, RegisterTable, Source};
use std::sync::Arc;
use std::time::Instant;
use testkit::fixtures::MODBUS_MAP;
use testkit::rng::Rng;

/// Frames in the storm.
const FRAMES: u64 = 1_000_000;

/// The card's outputs with a stand-in for its line: asked where a write stands, it takes
/// the card's pending writes and delivers them (no unit is behind this card), so the
/// server's wait for delivery ends at once and every write goes through it.
struct Delivered(Arc<ModbusCard>);

impl Delivered {
    fn settle(&self) {
        for w in self.0.take_writes() {
            self.0.write_delivered(&w);
        }
    }
}

impl Device for Delivered {
    fn health(&self) -> Health {
        self.0.health()
    }
}

impl AnalogOut for Delivered {
    fn channel_count(&self) -> u32 {
        AnalogOut::channel_count(&*self.0)
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        AnalogOut::scale(&*self.0, channel)
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.0.write_raw(channel, raw)
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.0.read_back_raw(channel)
    }
    fn delivery(&self, channel: u32) -> Option<Delivery> {
        self.settle();
        AnalogOut::delivery(&*self.0, channel)
    }
}

impl DigitalOut for Delivered {
    fn output_count(&self) -> u32 {
        self.0.output_count()
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.0.set_bit(bit, value)
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.0.check_bit(bit)
    }
    fn delivery(&self, bit: u32) -> Option<Delivery> {
        self.settle();
        DigitalOut::delivery(&*self.0, bit)
    }
}

fn table() -> RegisterTable {
    let card = driver_modbus::testing::card(MODBUS_MAP, 4);
    card.poll_succeeded();
    let outputs = Arc::new(Delivered(card.clone()));
    let (ai, ao): (Arc<dyn AnalogIn>, Arc<dyn AnalogOut>) = (card.clone(), outputs.clone());
    let (di, dout): (Arc<dyn DigitalIn>, Arc<dyn DigitalOut>) = (card.clone(), outputs);
    let layout = |ty| Layout {
        ty,
        words: WordOrder::HighFirst,
        bytes: ByteOrder::Normal,
    };
    let e = |table, address, ty, source| Entry {
        table,
        address,
        layout: layout(ty),
        scale: 0.1,
        offset: 0.0,
        source,
    };
    RegisterTable::new(vec![
        e(
            Table::InputRegisters,
            0,
            ValueType::I16,
            Source::AnalogIn(ai.clone(), 0),
        ),
        e(
            Table::InputRegisters,
            1,
            ValueType::F32,
            Source::AnalogIn(ai, 1),
        ),
        e(
            Table::HoldingRegisters,
            10,
            ValueType::U16,
            Source::AnalogOut(ao.clone(), 0),
        ),
        e(
            Table::HoldingRegisters,
            11,
            ValueType::I32,
            Source::AnalogOut(ao, 1),
        ),
        e(
            Table::DiscreteInputs,
            0,
            ValueType::U16,
            Source::DigitalIn(di, 0),
        ),
        e(
            Table::Coils,
            5,
            ValueType::U16,
            Source::DigitalOut(dout.clone(), 0),
        ),
        e(Table::Coils, 6, ValueType::U16, Source::DigitalOut(dout, 1)),
    ])
    .unwrap()
}

/// Valid requests of every function, to mutate.
fn seeds() -> Vec<Vec<u8>> {
    vec![
        vec![1, 0, 5, 0, 2],
        vec![2, 0, 0, 0, 1],
        vec![3, 0, 10, 0, 3],
        vec![4, 0, 0, 0, 3],
        vec![5, 0, 5, 0xFF, 0],
        vec![6, 0, 10, 0, 42],
        vec![15, 0, 5, 0, 2, 1, 0b11],
        vec![16, 0, 11, 0, 2, 4, 0xFF, 0xFE, 0xEE, 0x90],
    ]
}

/// The exception the Modbus specification (v1.1b3, §6 and its state diagrams) gives a
/// request for its shape alone, written out here apart from hwgw's `pdu` module: None for
/// a well-formed request, which the table then answers (a reply, 02 for an address it
/// does not serve, 03 for a value a device refuses, 04 for a device that fails).
fn spec_exception(req: &[u8]) -> Option<u8> {
    let Some(&f) = req.first() else {
        return Some(1);
    };
    let word = |i: usize| u16::from_be_bytes([req[i], req[i + 1]]);
    let past_end = |start: u16, q: u16| u32::from(start) + u32::from(q) > 0x1_0000;
    match f {
        1..=4 => {
            let limit = if f <= 2 { 0x07D0 } else { 0x007D };
            if req.len() != 5 || word(3) == 0 || word(3) > limit {
                Some(3)
            } else if past_end(word(1), word(3)) {
                Some(2)
            } else {
                None
            }
        }
        5 => (req.len() != 5 || !matches!(word(3), 0x0000 | 0xFF00)).then_some(3),
        6 => (req.len() != 5).then_some(3),
        15 | 16 => {
            if req.len() < 6 {
                return Some(3);
            }
            let (q, n) = (word(3), usize::from(req[5]));
            let (limit, bytes) = if f == 15 {
                (0x07B0, usize::from(q).div_ceil(8))
            } else {
                (0x007B, 2 * usize::from(q))
            };
            if q == 0 || q > limit || n != bytes || req.len() != 6 + n {
                Some(3)
            } else if past_end(word(1), q) {
                Some(2)
            } else {
                None
            }
        }
        _ => Some(1),
    }
}

/// Checks a reply PDU against its request: the specification's exception where the
/// request's shape calls for one, else a reply of the function's own shape or an
/// exception the table may give.
fn check_reply(req: &[u8], reply: &[u8]) {
    let f = req.first().copied().unwrap_or(0);
    assert!(
        !reply.is_empty() && reply.len() <= 253,
        "{req:x?} -> {reply:x?}"
    );
    if let Some(code) = spec_exception(req) {
        assert_eq!(reply, [f | 0x80, code], "{req:x?}");
        return;
    }
    if reply[0] & 0x80 != 0 {
        assert_eq!(reply.len(), 2, "{req:x?} -> {reply:x?}");
        assert_eq!(reply[0], f | 0x80, "{req:x?} -> {reply:x?}");
        let allowed: &[u8] = if matches!(f, 5 | 6 | 15 | 16) {
            &[2, 3, 4]
        } else {
            &[2, 4]
        };
        assert!(allowed.contains(&reply[1]), "{req:x?} -> {reply:x?}");
        return;
    }
    assert_eq!(reply[0], f, "{req:x?} -> {reply:x?}");
    match f {
        1..=4 => {
            let q = usize::from(u16::from_be_bytes([req[3], req[4]]));
            let bytes = if f <= 2 { q.div_ceil(8) } else { 2 * q };
            assert_eq!(usize::from(reply[1]), bytes, "{req:x?} -> {reply:x?}");
            assert_eq!(reply.len(), bytes + 2, "{req:x?} -> {reply:x?}");
        }
        5 | 6 | 15 | 16 => assert_eq!(reply, &req[..5], "{req:x?} -> {reply:x?}"),
        _ => panic!("function {f} answered: {req:x?} -> {reply:x?}"),
    }
}

#[test]
fn a_million_hostile_requests_no_panic_and_well_formed_replies() {
    let table = table();
    let seeds = seeds();
    let mut rng = Rng::new(0x005E_ED0F_F022);
    let (mut out, mut frame) = (Vec::with_capacity(260), Vec::with_capacity(260));
    let (mut exceptions, mut answered) = (0u64, 0u64);
    let t0 = Instant::now();
    for i in 0..FRAMES {
        frame.clear();
        if i % 2 == 0 {
            let len = rng.below(254) as usize;
            frame.extend((0..len).map(|_| rng.next_u64() as u8));
            if len > 0 && rng.below(2) == 0 {
                frame[0] = [1, 2, 3, 4, 5, 6, 15, 16][rng.below(8) as usize];
            }
        } else {
            frame.extend_from_slice(&seeds[rng.below(seeds.len() as u64) as usize]);
            for _ in 0..=rng.below(3) {
                match rng.below(4) {
                    0 if !frame.is_empty() => {
                        let at = rng.below(frame.len() as u64) as usize;
                        frame[at] = rng.next_u64() as u8;
                    }
                    1 => frame.push(rng.next_u64() as u8),
                    2 if frame.len() > 1 => {
                        frame.pop();
                    }
                    _ if frame.len() >= 5 => {
                        // A quantity at the limits and past them.
                        let q = [
                            0u16, 1, 123, 124, 125, 126, 1968, 1969, 2000, 2001, 0x7FFF, 0x8000,
                            0xFFFF,
                        ];
                        let q = q[rng.below(q.len() as u64) as usize].to_be_bytes();
                        frame[3] = q[0];
                        frame[4] = q[1];
                    }
                    _ => {}
                }
            }
        }
        out.clear();
        match pdu::parse(&frame) {
            Ok(req) => match table.answer(req) {
                Ok(a) => {
                    pdu::encode(&a.reply, &mut out);
                    answered += 1;
                }
                Err(code) => {
                    pdu::encode_refusal(
                        Refusal {
                            function: frame[0],
                            code,
                        },
                        &mut out,
                    );
                    exceptions += 1;
                }
            },
            Err(r) => {
                pdu::encode_refusal(r, &mut out);
                exceptions += 1;
            }
        }
        check_reply(&frame, &out);
    }
    let s = t0.elapsed().as_secs_f64();
    println!(
        "{FRAMES} frames in {s:.2} s ({:.0}/s): {answered} answered, {exceptions} exceptions, 0 panics",
        FRAMES as f64 / s
    );
    assert!(
        answered > 10_000 && exceptions > 100_000,
        "{answered} {exceptions}"
    );
}

/// The storm's kind of frames, 20 000 of them, through the real server over one TCP
/// connection: each answered and well formed, the server still running and answering a
/// plain read after it.
#[test]
fn the_server_answers_every_hostile_frame_over_tcp() {
    use driver_modbus::listener::{Limits, ModbusServer};
    use std::io::{Read, Write};
    let server =
        ModbusServer::start("127.0.0.1:0".parse().unwrap(), table(), Limits::default()).unwrap();
    let mut s = std::net::TcpStream::connect(server.addr()).unwrap();
    s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
        .unwrap();
    let seeds = seeds();
    let mut rng = Rng::new(0x0BAD_5EED);
    let mut frame = Vec::new();
    for i in 0..20_000u32 {
        let mut pdu: Vec<u8> = if i % 2 == 0 {
            (0..1 + rng.below(252))
                .map(|_| rng.next_u64() as u8)
                .collect()
        } else {
            seeds[rng.below(seeds.len() as u64) as usize].clone()
        };
        let at = rng.below(pdu.len() as u64) as usize;
        pdu[at] ^= rng.next_u64() as u8;
        frame.clear();
        frame.extend_from_slice(&(i as u16).to_be_bytes());
        frame.extend_from_slice(&[0, 0]);
        frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
        frame.push(1);
        frame.extend_from_slice(&pdu);
        s.write_all(&frame).unwrap();
        let mut head = [0u8; 7];
        s.read_exact(&mut head).unwrap();
        assert_eq!(head[..2], (i as u16).to_be_bytes());
        let mut body = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]])) - 1];
        s.read_exact(&mut body).unwrap();
        check_reply(&pdu, &body);
    }
    let c = server.counters();
    assert!(c.running && c.panics == 0 && c.requests == 20_000, "{c:?}");
    // Every write waited for its delivery, and had it.
    assert!(
        c.writes_confirmed > 100 && c.writes_failed == 0 && c.writes_unconfirmed == 0,
        "{c:?}"
    );
    // A plain read still answers.
    s.write_all(&[0, 1, 0, 0, 0, 6, 1, 4, 0, 0, 0, 1]).unwrap();
    let mut reply = [0u8; 11];
    s.read_exact(&mut reply).unwrap();
    assert_eq!(reply[7..9], [4, 2]);
}

/// Frames whose MBAP header is mutated (transaction and protocol ids, length, unit), each
/// on a connection of its own that the client then half-closes: whatever comes back is
/// whole Modbus TCP frames (a reply per request the server could frame), or nothing where
/// the header is not Modbus; the server keeps running, panics nothing and answers after.
#[test]
fn mutated_mbap_headers_are_answered_or_closed_never_more() {
    use driver_modbus::listener::{Limits, ModbusServer};
    use std::io::{Read, Write};
    let server =
        ModbusServer::start("127.0.0.1:0".parse().unwrap(), table(), Limits::default()).unwrap();
    let seeds = seeds();
    let mut rng = Rng::new(0x4D42_4150);
    for i in 0..2_000u32 {
        let pdu = &seeds[rng.below(seeds.len() as u64) as usize];
        let mut frame = Vec::new();
        frame.extend_from_slice(&(i as u16).to_be_bytes());
        frame.extend_from_slice(&[0, 0]);
        frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
        frame.push(1);
        frame.extend_from_slice(pdu);
        let field = rng.below(4);
        match field {
            0 => frame[2 + rng.below(2) as usize] = rng.next_u64() as u8,
            1 => {
                let len =
                    [0u16, 1, 2, 255, 256, 0xFFFF, rng.next_u64() as u16][rng.below(7) as usize];
                frame[4..6].copy_from_slice(&len.to_be_bytes());
            }
            2 => frame[6] = rng.next_u64() as u8,
            _ => frame.truncate(rng.below(frame.len() as u64) as usize),
        }
        let mut s = std::net::TcpStream::connect(server.addr()).unwrap();
        s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .unwrap();
        // The server may have closed already (a foreign header): a write or shutdown that
        // fails then is the server's answer, not the test's failure.
        let _ = s.write_all(&frame);
        let _ = s.shutdown(std::net::Shutdown::Write);
        let mut back = Vec::new();
        // End of file or a reset: the server closed the connection either way.
        let _ = s.read_to_end(&mut back);
        let mut rest = &back[..];
        while !rest.is_empty() {
            assert!(rest.len() >= 9, "{frame:x?} -> {back:x?}");
            let len = usize::from(u16::from_be_bytes([rest[4], rest[5]]));
            assert_eq!(rest[2..4], [0, 0], "{frame:x?} -> {back:x?}");
            assert!(rest.len() >= 6 + len, "{frame:x?} -> {back:x?}");
            rest = &rest[6 + len..];
        }
        if frame.len() >= 7 && frame[2..4] != [0, 0] {
            assert!(
                back.is_empty(),
                "a foreign protocol id answered: {frame:x?}"
            );
        }
    }
    let c = server.counters();
    assert!(c.running && c.panics == 0, "{c:?}");
    assert!(server.health().is_ok());
    let mut s = std::net::TcpStream::connect(server.addr()).unwrap();
    s.write_all(&[0, 1, 0, 0, 0, 6, 1, 4, 0, 0, 0, 1]).unwrap();
    let mut reply = [0u8; 11];
    s.read_exact(&mut reply).unwrap();
    assert_eq!(reply[7..9], [4, 2]);
}
