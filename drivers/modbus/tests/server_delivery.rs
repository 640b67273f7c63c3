//! The server's answer to a write whose device carries it later (a Modbus unit behind
//! hwgw's client, another gateway's output): sent only once the write is settled —
//! delivered, the normal reply; failed, 04 (refused on the way) or 0x0B (its target
//! offline); still on its way after `write_confirm`, 0x0B — and counted. While one
//! connection waits, another master is served. A device that applies its writes within the
//! call is answered at once, as before.
//!
//! The device is a stand-in whose bus is the test: a write is numbered when taken and
//! stays on its way until the test delivers or fails it (or is settled as it is taken, for
//! mbpoll, which gives up after its own 1 s timeout).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::time::Timestamp;
use device_interface::{
    AnalogOut, Delivery, DeliveryTracker, Device, DeviceError, DigitalOut, Health, RawRange, Scale,
    Unit,
};
use driver_modbus::codec::{ByteOrder, Layout, ValueType, WordOrder};
use driver_modbus::listener::{Limits, ModbusServer, ServerCounters};
use driver_modbus::plan::Table;
use driver_modbus::server::{Entry, RegisterTable, Source};
use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use testkit::mbpoll::Mbpoll;
use testkit::wait::PATIENCE;
use testkit::wait_until;

/// Two analog outputs and two digital outputs. With `tracking`, each write is numbered
/// and waits for the test (or for `at_once`); without, a write is applied within the call
/// (no delivery reported).
struct Relay {
    tracking: bool,
    analog: Mutex<[i64; 2]>,
    digital: Mutex<[bool; 2]>,
    analog_delivery: DeliveryTracker,
    digital_delivery: DeliveryTracker,
    /// Settles each write as it is taken: delivered (`Ok`) or failed for the reason.
    at_once: Mutex<Option<Result<(), DeviceError>>>,
}

impl Relay {
    fn new(tracking: bool) -> Arc<Relay> {
        Arc::new(Relay {
            tracking,
            analog: Mutex::new([0; 2]),
            digital: Mutex::new([false; 2]),
            analog_delivery: DeliveryTracker::new(2),
            digital_delivery: DeliveryTracker::new(2),
            at_once: Mutex::new(None),
        })
    }

    /// Every later write settled as it is taken, as `how` says.
    fn settle_at_once(&self, how: Result<(), DeviceError>) {
        *self.at_once.lock().unwrap() = Some(how);
    }

    fn taken(&self, t: &DeliveryTracker, ch: u32) {
        let n = t.take(ch);
        match self.at_once.lock().unwrap().clone() {
            Some(Ok(())) => t.delivered(ch, n),
            Some(Err(why)) => t.failed(ch, n, why),
            None => {}
        }
    }
}

fn scale() -> Scale {
    Scale::from_factor(
        RawRange::new(-32768, 32767).unwrap(),
        1.0,
        0.0,
        Unit::none(),
    )
    .unwrap()
}

fn check_channel(ch: u32) -> Result<usize, DeviceError> {
    if ch < 2 {
        Ok(ch as usize)
    } else {
        Err(DeviceError::ChannelOutOfRange {
            channel: ch,
            count: 2,
        })
    }
}

impl Device for Relay {
    fn health(&self) -> Health {
        Health::online_if(true, 1, Timestamp::from_nanos(1))
    }
}

impl AnalogOut for Relay {
    fn channel_count(&self) -> u32 {
        2
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        check_channel(channel)?;
        Ok(scale())
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        let i = check_channel(channel)?;
        scale().check_raw(channel, raw)?;
        self.analog.lock().unwrap()[i] = raw;
        self.taken(&self.analog_delivery, channel);
        Ok(())
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        Ok(self.analog.lock().unwrap()[check_channel(channel)?])
    }
    fn delivery(&self, channel: u32) -> Option<Delivery> {
        self.tracking.then(|| self.analog_delivery.get(channel))
    }
}

impl DigitalOut for Relay {
    fn output_count(&self) -> u32 {
        2
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        let i = check_channel(bit).map_err(|_| DeviceError::BitOutOfRange { bit, count: 2 })?;
        self.digital.lock().unwrap()[i] = value;
        self.taken(&self.digital_delivery, bit);
        Ok(())
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        let i = check_channel(bit).map_err(|_| DeviceError::BitOutOfRange { bit, count: 2 })?;
        Ok(self.digital.lock().unwrap()[i])
    }
    fn delivery(&self, bit: u32) -> Option<Delivery> {
        self.tracking.then(|| self.digital_delivery.get(bit))
    }
}

/// Holding registers 0 and 1 and coils 0 and 1 on `relay`'s outputs; input register 5 reads
/// analog output 0 back.
fn table(relay: &Arc<Relay>) -> RegisterTable {
    let (ao, dout): (Arc<dyn AnalogOut>, Arc<dyn DigitalOut>) = (relay.clone(), relay.clone());
    let e = |table, address, source| Entry {
        table,
        address,
        layout: Layout {
            ty: ValueType::I16,
            words: WordOrder::HighFirst,
            bytes: ByteOrder::Normal,
        },
        scale: 1.0,
        offset: 0.0,
        source,
    };
    RegisterTable::new(vec![
        e(Table::HoldingRegisters, 0, Source::AnalogOut(ao.clone(), 0)),
        e(Table::HoldingRegisters, 1, Source::AnalogOut(ao.clone(), 1)),
        e(Table::InputRegisters, 5, Source::AnalogOut(ao, 0)),
        e(Table::Coils, 0, Source::DigitalOut(dout.clone(), 0)),
        e(Table::Coils, 1, Source::DigitalOut(dout, 1)),
    ])
    .unwrap()
}

fn start(relay: &Arc<Relay>, write_confirm: Duration) -> ModbusServer {
    let limits = Limits {
        write_confirm,
        ..Limits::default()
    };
    ModbusServer::start("127.0.0.1:0".parse().unwrap(), table(relay), limits).unwrap()
}

/// Longer than any test runs: the bound never answers for the device.
const FOREVER: Duration = Duration::from_secs(600);

fn connect(server: &ModbusServer) -> TcpStream {
    let s = TcpStream::connect(server.addr()).unwrap();
    // Not a timed assertion: a server that never answers fails the test instead of
    // hanging it.
    s.set_read_timeout(Some(PATIENCE)).unwrap();
    s
}

/// Sends one request (unit 1).
fn send(s: &mut TcpStream, tid: u16, pdu: &[u8]) {
    let mut frame = tid.to_be_bytes().to_vec();
    frame.extend_from_slice(&[0, 0]);
    frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    frame.push(1);
    frame.extend_from_slice(pdu);
    s.write_all(&frame).unwrap();
}

/// The reply PDU to request `tid`.
fn receive(s: &mut TcpStream, tid: u16) -> Vec<u8> {
    let mut head = [0u8; 7];
    s.read_exact(&mut head).unwrap();
    assert_eq!(head[..2], tid.to_be_bytes(), "the transaction id echoed");
    let mut body = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]])) - 1];
    s.read_exact(&mut body).unwrap();
    body
}

fn exchange(s: &mut TcpStream, tid: u16, pdu: &[u8]) -> Vec<u8> {
    send(s, tid, pdu);
    receive(s, tid)
}

/// True when a reply (or anything) has arrived on `s`; does not wait.
fn answered(s: &TcpStream) -> bool {
    s.set_nonblocking(true).unwrap();
    let mut b = [0u8; 1];
    let r = s.peek(&mut b);
    s.set_nonblocking(false).unwrap();
    match r {
        Ok(_) => true,
        Err(e) if e.kind() == ErrorKind::WouldBlock => false,
        Err(e) => panic!("the connection failed: {e}"),
    }
}

/// The write counters: (confirmed, failed, unconfirmed).
fn writes(c: &ServerCounters) -> (u64, u64, u64) {
    (c.writes_confirmed, c.writes_failed, c.writes_unconfirmed)
}

#[test]
fn a_write_is_answered_once_delivered_and_other_masters_are_served_meanwhile() {
    let relay = Relay::new(true);
    let server = start(&relay, FOREVER);
    let mut waiting = connect(&server);
    send(&mut waiting, 7, &[6, 0, 0, 0, 123]);
    wait_until("the write taken", || relay.analog_delivery.taken(0) == 1);

    // Another master (mbpoll, a libmodbus master) reads while the write waits: the
    // server's single thread is not held by the wait.
    let read = Mbpoll {
        port: server.addr().port(),
        table: "3",
        address: 5,
        count: None,
        write: &[],
    }
    .run();
    assert!(read.contains("[5]: \t123"), "{read}");
    // The server answered that read after its turn with the waiting connection: had it
    // answered the write, the reply would be here by now.
    assert!(
        !answered(&waiting),
        "answered before the write was delivered"
    );
    assert_eq!(writes(&server.counters()), (0, 0, 0));

    relay.analog_delivery.delivered(0, 1);
    assert_eq!(receive(&mut waiting, 7), [6, 0, 0, 0, 123]);
    assert_eq!(writes(&server.counters()), (1, 0, 0));

    // Two coils in one request: answered once both are delivered.
    send(&mut waiting, 8, &[15, 0, 0, 0, 2, 1, 0b11]);
    wait_until("both coils taken", || {
        relay.digital_delivery.taken(0) == 1 && relay.digital_delivery.taken(1) == 1
    });
    relay.digital_delivery.delivered(1, 1);
    let mut other = connect(&server);
    assert_eq!(exchange(&mut other, 1, &[1, 0, 0, 0, 2]), [1, 1, 0b11]);
    assert!(!answered(&waiting), "answered with one coil on its way");
    relay.digital_delivery.delivered(0, 1);
    assert_eq!(receive(&mut waiting, 8), [15, 0, 0, 0, 2]);
    let c = server.counters();
    assert_eq!(writes(&c), (2, 0, 0));
    assert_eq!(c.exceptions, 0, "{c:?}");
}

#[test]
fn a_failed_write_is_answered_04_when_refused_and_0b_when_its_target_is_offline() {
    let relay = Relay::new(true);
    let server = start(&relay, FOREVER);
    let port = server.addr().port();
    let mbpoll = |table, write: &[&str]| {
        Mbpoll {
            port,
            table,
            address: 0,
            count: None,
            write,
        }
        .run()
    };

    // mbpoll gives up after 1 s: these writes are settled as they are taken.
    relay.settle_at_once(Err(DeviceError::Undelivered {
        reason: "the Modbus unit refused it: exception IllegalDataValue (0x03)",
    }));
    let refused = mbpoll("4", &["42"]);
    assert!(
        refused.contains("Slave device or server failure"),
        "{refused}"
    );
    relay.settle_at_once(Err(DeviceError::Offline));
    let offline = mbpoll("0", &["1"]);
    assert!(
        offline.contains("Target device failed to respond"),
        "{offline}"
    );
    relay.settle_at_once(Ok(()));
    let delivered = mbpoll("4", &["43"]);
    assert!(delivered.contains("Written 1 references"), "{delivered}");
    assert_eq!(writes(&server.counters()), (1, 2, 0));

    // Failed while the master waits: the answer comes as soon as one write fails, the
    // other still on its way.
    *relay.at_once.lock().unwrap() = None;
    let mut s = connect(&server);
    send(&mut s, 3, &[16, 0, 0, 0, 2, 4, 0, 1, 0, 2]);
    wait_until("both registers taken", || {
        relay.analog_delivery.taken(0) == 3 && relay.analog_delivery.taken(1) == 1
    });
    assert!(!answered(&s), "answered before either write settled");
    relay.analog_delivery.failed(
        1,
        1,
        DeviceError::Undelivered {
            reason: "the Modbus line stopped before the write was sent",
        },
    );
    assert_eq!(receive(&mut s, 3), [0x90, 0x04]);

    send(&mut s, 4, &[5, 0, 1, 0xFF, 0]);
    wait_until("the coil taken", || relay.digital_delivery.taken(1) == 1);
    relay.digital_delivery.failed(1, 1, DeviceError::Offline);
    assert_eq!(receive(&mut s, 4), [0x85, 0x0B]);
    let c = server.counters();
    assert_eq!(writes(&c), (1, 4, 0), "{c:?}");
    assert_eq!(c.exceptions, 4, "{c:?}");
}

#[test]
fn a_write_still_on_its_way_after_write_confirm_is_answered_0b() {
    let relay = Relay::new(true);
    let server = start(&relay, Duration::from_millis(50));
    let mut s = connect(&server);
    // Nobody delivers it: after 50 ms the master hears that the target did not respond.
    assert_eq!(exchange(&mut s, 1, &[6, 0, 1, 0, 9]), [0x86, 0x0B]);
    assert_eq!(exchange(&mut s, 2, &[5, 0, 0, 0xFF, 0]), [0x85, 0x0B]);
    let c = server.counters();
    assert_eq!(writes(&c), (0, 0, 2), "{c:?}");
    // The device took them: they may still arrive (the bound only ends the wait).
    assert_eq!(relay.read_back_raw(1).unwrap(), 9);
    assert_eq!(relay.analog_delivery.taken(1), 1);
    // The connection serves on.
    assert_eq!(exchange(&mut s, 3, &[3, 0, 1, 0, 1]), [3, 2, 0, 9]);
}

#[test]
fn a_device_without_delivery_tracking_is_answered_at_once() {
    let relay = Relay::new(false);
    let server = start(&relay, FOREVER);
    let mut s = connect(&server);
    assert_eq!(exchange(&mut s, 1, &[6, 0, 0, 0, 5]), [6, 0, 0, 0, 5]);
    assert_eq!(
        exchange(&mut s, 2, &[15, 0, 0, 0, 2, 1, 1]),
        [15, 0, 0, 0, 2]
    );
    assert_eq!(writes(&server.counters()), (0, 0, 0));
    assert_eq!(relay.read_back_raw(0).unwrap(), 5);
}
