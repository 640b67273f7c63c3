//! The server's connection limits against a lock-out: with every slot taken by idle
//! connections, or by connections stopped in the middle of a frame, a real master (mbpoll,
//! a libmodbus master) is still served — the connection idle longest is closed for it, and
//! counted; one address cannot take more than its share (refused, counted); a frame begun
//! and not finished closes its connection well before the idle timeout.
//!
//! The connections that take the slots come from other loopback addresses (127.0.0.x):
//! mbpoll always connects from 127.0.0.1.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::AnalogOut;
use driver_modbus::codec::{ByteOrder, Layout, ValueType, WordOrder};
use driver_modbus::listener::{Limits, ModbusServer, ServerCounters};
use driver_modbus::plan::Table;
use driver_modbus::server::{Entry, RegisterTable, Source};
use std::io::{ErrorKind, Read, Write};
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, TcpStream};
use std::sync::Arc;
use std::time::Duration;
use testkit::fixtures::MODBUS_MAP;
use testkit::mbpoll::Mbpoll;
use testkit::wait_until;

/// Holding registers 10 = 4321 and 11 = 1234 (a Modbus card's two analog outputs, as
/// written last).
fn table() -> RegisterTable {
    let card = driver_modbus::testing::card(MODBUS_MAP, 4);
    card.poll_succeeded();
    card.write(0, 4321.0).unwrap();
    card.write(1, 1234.0).unwrap();
    let ao: Arc<dyn AnalogOut> = card;
    let e = |address, channel| Entry {
        table: Table::HoldingRegisters,
        address,
        layout: Layout {
            ty: ValueType::U16,
            words: WordOrder::HighFirst,
            bytes: ByteOrder::Normal,
        },
        scale: 1.0,
        offset: 0.0,
        source: Source::AnalogOut(ao.clone(), channel),
    };
    RegisterTable::new(vec![e(10, 0), e(11, 1)]).unwrap()
}

fn start(limits: Limits) -> ModbusServer {
    ModbusServer::start("127.0.0.1:0".parse().unwrap(), table(), limits).unwrap()
}

/// A connection to `to` from the loopback address 127.0.0.`host`.
fn connect_from(host: u8, to: SocketAddr) -> TcpStream {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let s = rt
        .block_on(async {
            let socket = tokio::net::TcpSocket::new_v4()?;
            socket.bind(SocketAddrV4::new(Ipv4Addr::new(127, 0, 0, host), 0).into())?;
            socket.connect(to).await?.into_std()
        })
        .unwrap();
    s.set_nonblocking(false).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s
}

/// One request over `s` (unit 1); the reply's PDU, or None when the connection is closed.
fn exchange(s: &mut TcpStream, tid: u16, pdu: &[u8]) -> Option<Vec<u8>> {
    let mut frame = tid.to_be_bytes().to_vec();
    frame.extend_from_slice(&[0, 0]);
    frame.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    frame.push(1);
    frame.extend_from_slice(pdu);
    s.write_all(&frame).ok()?;
    let mut head = [0u8; 7];
    s.read_exact(&mut head).ok()?;
    assert_eq!(head[..2], tid.to_be_bytes(), "the transaction id echoed");
    let mut body = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]])) - 1];
    s.read_exact(&mut body).ok()?;
    Some(body)
}

/// FC3 of holding register 10 and its reply (4321 = 0x10E1).
const READ_HR10: [u8; 5] = [3, 0, 10, 0, 1];
const HR10: [u8; 4] = [3, 2, 0x10, 0xE1];

/// True when the server has closed `s` (end of file or a reset), false while it is open;
/// does not wait.
fn closed(s: &TcpStream) -> bool {
    s.set_nonblocking(true).unwrap();
    let mut b = [0u8; 1];
    let r = (&*s).read(&mut b);
    s.set_nonblocking(false).unwrap();
    match r {
        Ok(0) => true,
        Ok(_) => panic!("the server sent a byte nobody asked for"),
        Err(e) if e.kind() == ErrorKind::WouldBlock => false,
        Err(e) => matches!(
            e.kind(),
            ErrorKind::ConnectionReset | ErrorKind::ConnectionAborted | ErrorKind::BrokenPipe
        ),
    }
}

/// mbpoll's read of holding registers 10 and 11 from 127.0.0.1.
fn mbpoll(server: &ModbusServer) -> String {
    Mbpoll {
        port: server.addr().port(),
        table: "4",
        address: 10,
        count: Some(2),
        write: &[],
    }
    .run()
}

fn served(out: &str) -> bool {
    out.contains("[10]: \t4321") && out.contains("[11]: \t1234")
}

/// Opens `n` connections from 127.0.0.`first`, 127.0.0.`first + 1`, ..., each accepted
/// before the next is made (so the first is the one idle longest). Every connection made
/// before must have been accepted.
fn take_slots(server: &ModbusServer, first: u8, n: u8) -> Vec<TcpStream> {
    let before = server.counters().clients;
    (0..n)
        .map(|i| {
            let s = connect_from(first + i, server.addr());
            wait_until("the connection accepted", || {
                server.counters().clients == before + usize::from(i) + 1
            });
            s
        })
        .collect()
}

fn counters(server: &ModbusServer) -> ServerCounters {
    server.counters()
}

#[test]
fn sixteen_idle_connections_do_not_lock_out_a_master() {
    let server = start(Limits::default());
    let idle = take_slots(&server, 10, 16);
    assert_eq!(counters(&server).clients, 16);

    let out = mbpoll(&server);
    assert!(
        served(&out),
        "mbpoll is served with every slot idle:\n{out}"
    );
    let c = counters(&server);
    assert_eq!((c.evicted, c.refused_per_address), (1, 0), "{c:?}");
    assert_eq!(c.connections, 17, "{c:?}");
    // The one closed is the one idle longest: the first.
    wait_until("the idle-longest connection closed", || closed(&idle[0]));
    assert!(idle[1..].iter().all(|s| !closed(s)), "only one is closed");

    // With mbpoll gone a slot is free: the next master takes it and closes nobody.
    wait_until("mbpoll's connection gone", || {
        counters(&server).clients == 15
    });
    let out = mbpoll(&server);
    assert!(served(&out), "{out}");
    let c = counters(&server);
    assert_eq!(c.evicted, 1, "{c:?}");
    assert!(c.running && c.panics == 0, "{c:?}");
    assert!(server.health().is_ok());
}

/// Connections that stopped in the middle of a frame — of the header, or of the PDU after
/// it — are idle since their last complete request: sent bytes do not protect them. A
/// connection that completed a request after they were accepted is not the one closed.
#[test]
fn half_sent_frames_do_not_lock_out_a_master_nor_protect_their_connection() {
    // No frame timeout before the idle timeout: only an eviction can free a slot here.
    let server = start(Limits {
        frame_timeout: Duration::from_secs(60),
        ..Limits::default()
    });
    let mut half = take_slots(&server, 10, 15);
    let mut active = connect_from(30, server.addr());
    assert_eq!(exchange(&mut active, 1, &READ_HR10).unwrap(), HR10);
    for (i, s) in half.iter_mut().enumerate() {
        if i % 2 == 0 {
            s.write_all(&[0, 1, 0]).unwrap(); // 3 of the MBAP header's 7 bytes
        } else {
            s.write_all(&[0, 1, 0, 0, 0, 6, 1, 3, 0]).unwrap(); // the header, 2 of 5 PDU bytes
        }
    }
    assert_eq!(counters(&server).clients, 16);

    let out = mbpoll(&server);
    assert!(
        served(&out),
        "mbpoll is served with every slot taken:\n{out}"
    );
    let c = counters(&server);
    assert_eq!(c.evicted, 1, "{c:?}");
    wait_until("the half-sent frame's connection closed", || {
        closed(&half[0])
    });
    assert!(half[1..].iter().all(|s| !closed(s)), "only one is closed");
    // The connection with a complete request is still served.
    assert_eq!(exchange(&mut active, 2, &READ_HR10).unwrap(), HR10);
    let c = counters(&server);
    assert_eq!(
        (c.frame_timeouts, c.idle_closed, c.malformed),
        (0, 0, 0),
        "{c:?}"
    );
    assert!(c.running && c.panics == 0, "{c:?}");
}

#[test]
fn a_frame_stopped_midway_is_closed_after_the_frame_timeout_an_idle_one_is_not() {
    let server = start(Limits {
        frame_timeout: Duration::from_millis(200),
        ..Limits::default()
    });
    let mut quiet = take_slots(&server, 1, 1).remove(0);
    let slots = take_slots(&server, 2, 2);
    let (mut head, mut body) = (&slots[0], &slots[1]);
    head.write_all(&[0, 1, 0]).unwrap();
    body.write_all(&[0, 1, 0, 0, 0, 6, 1, 3, 0]).unwrap();
    wait_until("the half-sent frames closed", || {
        closed(head) && closed(body)
    });
    let c = counters(&server);
    assert_eq!((c.frame_timeouts, c.idle_closed), (2, 0), "{c:?}");
    // Connected before them, quiet for longer than the frame timeout: still served.
    assert_eq!(exchange(&mut quiet, 1, &READ_HR10).unwrap(), HR10);
    // A frame sent in pieces within the timeout is a frame.
    quiet.write_all(&[0, 2, 0, 0]).unwrap();
    quiet.write_all(&[0, 6, 1, 3, 0]).unwrap();
    quiet.write_all(&[10, 0, 1]).unwrap();
    let mut reply = [0u8; 11];
    quiet.read_exact(&mut reply).unwrap();
    assert_eq!(reply[7..], HR10);
    assert_eq!(counters(&server).evicted, 0);
}

/// One address gets `max_clients_per_address` connections; one more from it is refused
/// and counted, and does not evict anyone even when every slot is taken; the others'
/// addresses are served. mbpoll (from 127.0.0.1) is refused while its address has its
/// share, served once it has a slot again.
#[test]
fn one_address_gets_its_share_and_no_more() {
    let server = start(Limits {
        max_clients: 4,
        max_clients_per_address: 2,
        ..Limits::default()
    });
    let addr = server.addr();
    let mut mine: Vec<_> = (0..2).map(|_| connect_from(1, addr)).collect();
    let mut theirs: Vec<_> = (0..2).map(|_| connect_from(2, addr)).collect();
    for (i, s) in mine.iter_mut().chain(theirs.iter_mut()).enumerate() {
        assert_eq!(exchange(s, i as u16, &READ_HR10).unwrap(), HR10);
    }
    assert_eq!(counters(&server).clients, 4);

    // A third from 127.0.0.1: refused, though the pool is full and could evict.
    let third = connect_from(1, addr);
    wait_until("the third connection from one address closed", || {
        closed(&third)
    });
    let c = counters(&server);
    assert_eq!((c.refused_per_address, c.evicted), (1, 0), "{c:?}");
    let out = mbpoll(&server);
    assert!(
        !served(&out),
        "mbpoll refused: 127.0.0.1 has its two:\n{out}"
    );
    assert_eq!(counters(&server).refused_per_address, 2);
    for (i, s) in mine.iter_mut().chain(theirs.iter_mut()).enumerate() {
        assert_eq!(
            exchange(s, 10 + i as u16, &READ_HR10).unwrap(),
            HR10,
            "connection {i} still served"
        );
    }

    // One of 127.0.0.1's connections closed: mbpoll is served again, in the slot it left.
    drop(mine.remove(0));
    wait_until("the server sees it gone", || counters(&server).clients == 3);
    let out = mbpoll(&server);
    assert!(served(&out), "{out}");
    let c = counters(&server);
    assert_eq!((c.refused_per_address, c.evicted), (2, 0), "{c:?}");
    assert!(c.running && c.panics == 0, "{c:?}");
}

/// A device reopening sockets from one address (16, all kept open): it gets its share (8
/// by default), the rest is refused and counted, and a master elsewhere is served without
/// closing anyone.
#[test]
fn a_device_reopening_sockets_cannot_take_every_slot() {
    let server = start(Limits::default());
    let addr = server.addr();
    let device: Vec<_> = (0..16).map(|_| connect_from(2, addr)).collect();
    wait_until("8 admitted, 8 refused", || {
        let c = counters(&server);
        c.clients == 8 && c.refused_per_address == 8
    });
    wait_until("the refused ones closed", || {
        device.iter().filter(|s| closed(s)).count() == 8
    });
    let out = mbpoll(&server);
    assert!(served(&out), "{out}");
    let c = counters(&server);
    assert_eq!((c.evicted, c.refused_per_address), (0, 8), "{c:?}");
}
