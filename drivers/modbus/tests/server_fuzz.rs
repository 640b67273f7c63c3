//! The server's request path (the checks of `pdu`, the register table's answer, the reply's
//! encoding) under a seeded storm of random and mutated request PDUs: no panic, every reply
//! well formed, the exceptions the specification gives. Over the same devices a Modbus
//! card offers (a card built from the shared fixture map, online).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{AnalogIn, AnalogOut, DigitalIn, DigitalOut};
use driver_modbus::codec::{ByteOrder, Layout, ValueType, WordOrder};
use driver_modbus::pdu::{self, Refusal};
use driver_modbus::plan::Table;
use driver_modbus::server::{Entry, RegisterTable, Source};
use std::sync::Arc;
use std::time::Instant;
use testkit::fixtures::MODBUS_MAP;

/// Frames in the storm.
const FRAMES: u64 = 1_000_000;

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

fn table() -> RegisterTable {
    let card = driver_modbus::testing::card(MODBUS_MAP, 4);
    card.poll_succeeded();
    let (ai, ao): (Arc<dyn AnalogIn>, Arc<dyn AnalogOut>) = (card.clone(), card.clone());
    let (di, dout): (Arc<dyn DigitalIn>, Arc<dyn DigitalOut>) = (card.clone(), card.clone());
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

/// Checks a reply PDU's shape against its request.
fn check_reply(req: &[u8], reply: &[u8]) {
    let f = req.first().copied().unwrap_or(0);
    assert!(
        !reply.is_empty() && reply.len() <= 253,
        "{req:x?} -> {reply:x?}"
    );
    if reply[0] & 0x80 != 0 {
        assert_eq!(reply.len(), 2, "{req:x?} -> {reply:x?}");
        assert_eq!(reply[0], f | 0x80, "{req:x?} -> {reply:x?}");
        assert!((1..=4).contains(&reply[1]), "{req:x?} -> {reply:x?}");
        return;
    }
    assert_eq!(reply[0], f, "{req:x?} -> {reply:x?}");
    match f {
        1..=4 => assert_eq!(
            usize::from(reply[1]) + 2,
            reply.len(),
            "{req:x?} -> {reply:x?}"
        ),
        5 | 6 | 15 | 16 => assert_eq!(&reply[..5], &req[..5], "{req:x?} -> {reply:x?}"),
        _ => panic!("function {f} answered: {req:x?} -> {reply:x?}"),
    }
}

#[test]
fn a_million_hostile_requests_no_panic_and_well_formed_replies() {
    let table = table();
    let seeds = seeds();
    let mut rng = Rng(0x005E_ED0F_F022);
    let (mut out, mut frame) = (Vec::with_capacity(260), Vec::with_capacity(260));
    let (mut exceptions, mut answered) = (0u64, 0u64);
    let t0 = Instant::now();
    for i in 0..FRAMES {
        frame.clear();
        if i % 2 == 0 {
            let len = rng.below(254) as usize;
            frame.extend((0..len).map(|_| rng.next() as u8));
            if len > 0 && rng.below(2) == 0 {
                frame[0] = [1, 2, 3, 4, 5, 6, 15, 16][rng.below(8) as usize];
            }
        } else {
            frame.extend_from_slice(&seeds[rng.below(seeds.len() as u64) as usize]);
            for _ in 0..=rng.below(3) {
                match rng.below(4) {
                    0 if !frame.is_empty() => {
                        let at = rng.below(frame.len() as u64) as usize;
                        frame[at] = rng.next() as u8;
                    }
                    1 => frame.push(rng.next() as u8),
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
                Ok(resp) => {
                    pdu::encode(&resp, &mut out);
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
    let mut rng = Rng(0x0BAD_5EED);
    let mut frame = Vec::new();
    for i in 0..20_000u32 {
        let mut pdu: Vec<u8> = if i % 2 == 0 {
            (0..1 + rng.below(252)).map(|_| rng.next() as u8).collect()
        } else {
            seeds[rng.below(seeds.len() as u64) as usize].clone()
        };
        let at = rng.below(pdu.len() as u64) as usize;
        pdu[at] ^= rng.next() as u8;
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
    // A plain read still answers.
    s.write_all(&[0, 1, 0, 0, 0, 6, 1, 4, 0, 0, 0, 1]).unwrap();
    let mut reply = [0u8; 11];
    s.read_exact(&mut reply).unwrap();
    assert_eq!(reply[7..9], [4, 2]);
}
