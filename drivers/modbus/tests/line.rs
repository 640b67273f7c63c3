//! The line poller against a real Modbus TCP server (tokio-modbus's, in this process) with
//! injectable faults: values in and out, exceptions, a silent unit beside a healthy one,
//! a dropped connection.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::{AnalogIn, AnalogOut, Device, DeviceError, DigitalIn, DigitalOut, Status};
use driver_modbus::card::ModbusCard;
use driver_modbus::line::{LineUnit, Transport, UnitStats, UnitTiming};
use driver_modbus::testing::TestLine;
use driver_modbus::testing::TestServer;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use testkit::fixtures::MODBUS_MAP;
use testkit::wait_until;
use tokio_modbus::ExceptionCode;

fn card(map_text: &str) -> Arc<ModbusCard> {
    driver_modbus::testing::card(map_text, 4)
}

fn timing(unit: u8) -> UnitTiming {
    UnitTiming {
        unit,
        poll: Duration::from_millis(20),
        timeout: Duration::from_millis(100),
        stale_after: 2,
        offline_after: 4,
        backoff_max: Duration::from_millis(800),
    }
}

#[test]
fn values_in_and_out_over_tcp() {
    let server = TestServer::start();
    {
        let mut m = server.memory().lock().unwrap();
        m.input[0] = (-123i16) as u16;
        let f = 6.25f32.to_bits();
        m.input[1] = (f >> 16) as u16;
        m.input[2] = f as u16;
        m.holding[20] = 0x0001;
        m.holding[21] = 0x0002;
        m.discrete[3] = true;
    }
    let card = card(MODBUS_MAP);
    let stats = Arc::new(UnitStats::default());
    let _line = TestLine::spawn(
        "mb-test",
        Transport::Tcp(server.addr()),
        vec![LineUnit {
            card: card.clone(),
            timing: timing(1),
            stats: stats.clone(),
        }],
    )
    .unwrap();
    wait_until("online", || card.health().status == Status::Online);
    assert_eq!(card.read(0).unwrap(), -12.3);
    assert_eq!(card.read(1).unwrap(), 6.25);
    assert_eq!(card.read_raw(2).unwrap(), 0x0001_0002);
    assert!(card.read_bit(0).unwrap());

    card.write(0, 4321.0).unwrap();
    card.set_bit(0, true).unwrap();
    card.set_bit(1, true).unwrap();
    wait_until("writes reach the server", || {
        let m = server.memory().lock().unwrap();
        m.holding[10] == 4321 && m.coils[5] && m.coils[6]
    });
    assert_eq!(stats.timeouts.load(Ordering::Relaxed), 0);
    assert_eq!(stats.exceptions.load(Ordering::Relaxed), 0);
    assert!(stats.polls.load(Ordering::Relaxed) > 0);
}

#[test]
fn exceptions_surface_with_their_code_and_make_the_unit_stale_then_offline() {
    let server = TestServer::start();
    server.memory().lock().unwrap().holding_exception = Some(ExceptionCode::IllegalDataAddress);
    let card = card(MODBUS_MAP);
    let stats = Arc::new(UnitStats::default());
    let _line = TestLine::spawn(
        "mb-test",
        Transport::Tcp(server.addr()),
        vec![LineUnit {
            card: card.clone(),
            timing: timing(1),
            stats: stats.clone(),
        }],
    )
    .unwrap();
    wait_until("offline", || stats.exceptions.load(Ordering::Relaxed) >= 4);
    let h = card.health();
    assert_eq!(h.status, Status::Offline);
    let e = h.last_error.unwrap().to_string();
    assert!(
        e.contains("Modbus exception IllegalDataAddress (0x02)")
            && e.contains("FC3 read holding registers 20..=21"),
        "{e}"
    );
    server.memory().lock().unwrap().holding_exception = None;
    wait_until("back online", || card.health().status == Status::Online);
    assert_eq!(
        stats.timeouts.load(Ordering::Relaxed),
        0,
        "exceptions are answers, not timeouts"
    );
}

#[test]
fn a_silent_unit_does_not_stall_a_healthy_one_on_the_same_line() {
    let server = TestServer::start();
    server.memory().lock().unwrap().silent.insert(2);
    let healthy = card(MODBUS_MAP);
    let dead = card(MODBUS_MAP);
    let (hs, ds) = (
        Arc::new(UnitStats::default()),
        Arc::new(UnitStats::default()),
    );
    let _line = TestLine::spawn(
        "mb-test",
        Transport::Tcp(server.addr()),
        vec![
            LineUnit {
                card: healthy.clone(),
                timing: timing(1),
                stats: hs.clone(),
            },
            LineUnit {
                card: dead.clone(),
                timing: timing(2),
                stats: ds.clone(),
            },
        ],
    )
    .unwrap();
    // Every card starts offline ("never seen"): wait for the dead unit's real failures.
    wait_until("the dead unit failed into offline", || {
        ds.timeouts.load(Ordering::Relaxed) >= 4
    });
    wait_until("the healthy unit online", || {
        healthy.health().status == Status::Online
    });
    assert_eq!(dead.health().status, Status::Offline);
    let (polls0, probes0) = (
        hs.polls.load(Ordering::Relaxed),
        ds.requests.load(Ordering::Relaxed),
    );
    let t0 = Instant::now();
    let mut always_online = true;
    let mut seen = std::collections::BTreeMap::new();
    while t0.elapsed() < Duration::from_millis(2000) {
        let st = healthy.health().status;
        *seen.entry(format!("{st:?}")).or_insert(0) += 1;
        always_online &= st == Status::Online;
        std::thread::sleep(Duration::from_millis(5));
    }
    let elapsed = t0.elapsed();
    let polls = hs.polls.load(Ordering::Relaxed) - polls0;
    let probes = ds.requests.load(Ordering::Relaxed) - probes0;
    let nominal = elapsed.as_secs_f64() / 0.020;
    // A figure, not a timed assertion: printed for the record.
    eprintln!(
        "healthy unit: {polls} polls in {elapsed:?} = {:.0}% of its nominal {nominal:.0}; dead unit: {probes} probes",
        100.0 * polls as f64 / nominal
    );
    let c = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    assert!(
        always_online,
        "the healthy unit left online ({seen:?}): timeouts {}, transport {}, exceptions {}, bad {}; last error {:?}",
        c(&hs.timeouts),
        c(&hs.transport_errors),
        c(&hs.exceptions),
        c(&hs.bad_replies),
        healthy.health().last_error.map(|e| e.to_string())
    );
    // Backoff 400 ms doubling to 800 ms: at most one probe per 400 ms, plus one in flight.
    let max_probes = (elapsed.as_secs_f64() / 0.4).ceil() as u64 + 1;
    assert!(
        probes <= max_probes,
        "the dead unit is backed off, not hammered: {probes} probes > {max_probes}"
    );
    assert!(
        polls as f64 >= 0.5 * nominal,
        "the healthy unit is not stalled: {polls} polls"
    );
}

#[test]
fn a_lost_connection_is_reconnected() {
    let server = TestServer::start();
    let addr = server.addr();
    let card = card(MODBUS_MAP);
    let stats = Arc::new(UnitStats::default());
    let _line = TestLine::spawn(
        "mb-test",
        Transport::Tcp(addr),
        vec![LineUnit {
            card: card.clone(),
            timing: timing(1),
            stats: stats.clone(),
        }],
    )
    .unwrap();
    wait_until("online", || card.health().status == Status::Online);
    let mem = server.memory().clone();
    drop(server);
    wait_until("offline without the server", || {
        card.health().status == Status::Offline
    });
    let _again = TestServer::start_on(mem, addr);
    wait_until("online again by itself", || {
        card.health().status == Status::Online
    });
    assert!(
        stats.transport_errors.load(Ordering::Relaxed) + stats.timeouts.load(Ordering::Relaxed) > 0
    );
}

/// A raw Modbus TCP responder: for each request frame, `reply` returns the bytes to send
/// (and whether to close the connection afterwards) — for replies no real server sends.
fn raw_server(reply: fn(&[u8]) -> (Vec<u8>, bool)) -> std::net::SocketAddr {
    use std::io::{Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { return };
            std::thread::spawn(move || {
                loop {
                    let mut header = [0u8; 7];
                    if conn.read_exact(&mut header).is_err() {
                        return;
                    }
                    let len = usize::from(u16::from_be_bytes([header[4], header[5]]));
                    let mut pdu = vec![0u8; len.saturating_sub(1)];
                    if conn.read_exact(&mut pdu).is_err() {
                        return;
                    }
                    let mut request = header.to_vec();
                    request.extend_from_slice(&pdu);
                    let (bytes, close) = reply(&request);
                    if conn.write_all(&bytes).is_err() || close {
                        return;
                    }
                }
            });
        }
    });
    addr
}

/// A well-formed reply to a read of input registers, all zero, from `unit`.
fn zeros_from(request: &[u8], unit: u8) -> Vec<u8> {
    let count = u16::from_be_bytes([request[10], request[11]]);
    let bytes = (count * 2) as u8;
    let mut r = request[0..4].to_vec(); // transaction and protocol ids
    r.extend_from_slice(&(3 + u16::from(bytes)).to_be_bytes());
    r.push(unit);
    r.push(request[7]); // function code
    r.push(bytes);
    r.extend(std::iter::repeat_n(0u8, usize::from(bytes)));
    r
}

const ONE_INPUT: &str = "[[point]]\ntable = \"input_registers\"\naddress = 0\n";

fn line_against(addr: std::net::SocketAddr) -> (Arc<ModbusCard>, Arc<UnitStats>, TestLine) {
    let card = card(ONE_INPUT);
    let stats = Arc::new(UnitStats::default());
    let line = TestLine::spawn(
        "mb-raw",
        Transport::Tcp(addr),
        vec![LineUnit {
            card: card.clone(),
            timing: timing(1),
            stats: stats.clone(),
        }],
    )
    .unwrap();
    (card, stats, line)
}

#[test]
fn a_reply_from_the_wrong_unit_is_rejected_and_counted() {
    let addr = raw_server(|req| (zeros_from(req, req[6].wrapping_add(1)), false));
    let (card, stats, _line) = line_against(addr);
    wait_until("bad replies counted", || {
        stats.bad_replies.load(Ordering::Relaxed) >= 3
    });
    assert_ne!(
        card.health().status,
        Status::Online,
        "never online on replies from another unit"
    );
    let e = card.health().last_error.unwrap().to_string();
    eprintln!("wrong unit: {e}");
    assert_eq!(stats.polls.load(Ordering::Relaxed), 0);
}

#[test]
fn a_late_reply_to_another_transaction_is_dropped_and_counted() {
    // Before each right reply, a reply to the transaction before it (as a unit that
    // answers a timed-out request late would send): dropped, counted, the poll good.
    let addr = raw_server(|req| {
        let mut late = zeros_from(req, req[6]);
        let tid = u16::from_be_bytes([req[0], req[1]]).wrapping_sub(1);
        late[..2].copy_from_slice(&tid.to_be_bytes());
        late.extend(zeros_from(req, req[6]));
        (late, false)
    });
    let (card, stats, _line) = line_against(addr);
    wait_until("online", || card.health().status == Status::Online);
    // A stale reply is counted as it is read, its poll once the right reply after it is
    // in: both are waited for (under load the third poll came a moment after).
    wait_until("stale replies and good polls counted", || {
        stats.stale_replies.load(Ordering::Relaxed) >= 3 && stats.polls.load(Ordering::Relaxed) >= 3
    });
    assert_eq!(stats.bad_replies.load(Ordering::Relaxed), 0);
    assert_eq!(stats.transport_errors.load(Ordering::Relaxed), 0);
}

#[test]
fn a_truncated_frame_is_an_error_not_a_hang() {
    // The header promises 5 bytes of PDU; 2 arrive, then the connection closes.
    let addr = raw_server(|req| {
        let mut r = zeros_from(req, req[6]);
        r.truncate(9);
        (r, true)
    });
    let (card, stats, _line) = line_against(addr);
    wait_until("failures counted", || {
        stats.transport_errors.load(Ordering::Relaxed) + stats.timeouts.load(Ordering::Relaxed) >= 3
    });
    assert_ne!(card.health().status, Status::Online);
    eprintln!("truncated: {}", card.health().last_error.unwrap());
}

#[test]
fn a_slow_reply_within_the_timeout_is_fine_and_one_past_it_times_out() {
    let fast = raw_server(|req| {
        std::thread::sleep(Duration::from_millis(50)); // timeout is 100 ms
        (zeros_from(req, req[6]), false)
    });
    let (card, stats, line) = line_against(fast);
    wait_until("online despite the delay", || {
        card.health().status == Status::Online
    });
    assert_eq!(stats.timeouts.load(Ordering::Relaxed), 0);
    drop(line);
    let slow = raw_server(|req| {
        std::thread::sleep(Duration::from_millis(250));
        (zeros_from(req, req[6]), false)
    });
    let (card, stats, _line) = line_against(slow);
    wait_until("timeouts counted", || {
        stats.timeouts.load(Ordering::Relaxed) >= 2
    });
    assert_ne!(card.health().status, Status::Online);
    assert_eq!(stats.polls.load(Ordering::Relaxed), 0);
}

/// A line polling `card` as unit 1 at `server`, with `timing`.
fn line_with(
    name: &str,
    server: &TestServer,
    card: &Arc<ModbusCard>,
    timing: UnitTiming,
) -> (Arc<UnitStats>, TestLine) {
    let stats = Arc::new(UnitStats::default());
    let line = TestLine::spawn(
        name,
        Transport::Tcp(server.addr()),
        vec![LineUnit {
            card: card.clone(),
            timing,
            stats: stats.clone(),
        }],
    )
    .unwrap();
    (stats, line)
}

/// Where write `n` of analog output `ch` stands: None while on its way.
fn analog_outcome(card: &ModbusCard, ch: u32, n: u64) -> Option<Result<(), DeviceError>> {
    AnalogOut::delivery(card, ch).unwrap().outcome(n)
}

/// The number of the newest write to analog output `ch`.
fn analog_taken(card: &ModbusCard, ch: u32) -> u64 {
    AnalogOut::delivery(card, ch).unwrap().taken
}

/// Waits until write `n` of analog output `ch` is settled; its outcome.
fn settled(card: &ModbusCard, ch: u32, n: u64) -> Result<(), DeviceError> {
    let mut outcome = None;
    wait_until("the write settled", || {
        outcome = analog_outcome(card, ch, n);
        outcome.is_some()
    });
    outcome.unwrap()
}

#[test]
fn a_write_to_a_reachable_unit_settles_delivered() {
    let server = TestServer::start();
    let card = card(MODBUS_MAP);
    let (stats, _line) = line_with("mb-deliver", &server, &card, timing(1));
    wait_until("online", || card.health().status == Status::Online);
    card.write(0, 4321.0).unwrap();
    let n = analog_taken(&card, 0);
    card.set_bit(1, true).unwrap();
    let b = DigitalOut::delivery(&*card, 1).unwrap().taken;
    settled(&card, 0, n).unwrap();
    wait_until("the coil's write settled", || {
        DigitalOut::delivery(&*card, 1)
            .unwrap()
            .outcome(b)
            .is_some()
    });
    assert!(matches!(
        DigitalOut::delivery(&*card, 1).unwrap().outcome(b),
        Some(Ok(()))
    ));
    let m = server.memory().lock().unwrap();
    assert_eq!(
        (m.holding[10], m.coils[6]),
        (4321, true),
        "delivered means there"
    );
    assert_eq!(stats.writes_failed.load(Ordering::Relaxed), 0);
}

/// The unit stops answering with a write on its way: once it is declared offline the
/// write fails (Offline) — its writer is never left waiting.
#[test]
fn a_write_to_a_unit_that_stops_answering_fails_once_the_unit_is_offline() {
    let server = TestServer::start();
    let card = card(MODBUS_MAP);
    let (stats, line) = line_with("mb-down", &server, &card, timing(1));
    wait_until("online", || card.health().status == Status::Online);
    // The line paused, the unit silenced, a write: taken while the unit is online
    // (whatever the machine's load), then the line polls a unit that answers nothing.
    line.task().stop().unwrap();
    server.memory().lock().unwrap().silent.insert(1);
    assert_eq!(card.health().status, Status::Online);
    card.write(0, 777.0).unwrap();
    let n = analog_taken(&card, 0);
    assert!(analog_outcome(&card, 0, n).is_none(), "on its way");
    line.task().start().unwrap();
    let outcome = settled(&card, 0, n);
    assert!(matches!(outcome, Err(DeviceError::Offline)), "{outcome:?}");
    assert_eq!(card.health().status, Status::Offline);
    assert_eq!(server.memory().lock().unwrap().holding[10], 0);
    assert_eq!(stats.writes_failed.load(Ordering::Relaxed), 1);
    assert!(!card.deliveries_pending());
}

/// A write still on its way when the line stops fails: nothing will carry it.
#[test]
fn a_write_pending_when_the_line_stops_fails() {
    let server = TestServer::start();
    let card = card(MODBUS_MAP);
    // A unit that never goes offline here: only the stop ends the write's wait.
    let t = UnitTiming {
        offline_after: u32::MAX,
        stale_after: u32::MAX,
        ..timing(1)
    };
    let (stats, line) = line_with("mb-stop", &server, &card, t);
    wait_until("online", || card.health().status == Status::Online);
    server.memory().lock().unwrap().silent_writes = true;
    card.write(0, 55.0).unwrap();
    let n = analog_taken(&card, 0);
    wait_until("the write sent and unanswered", || {
        stats.write_retries.load(Ordering::Relaxed) >= 1
    });
    assert!(
        analog_outcome(&card, 0, n).is_none(),
        "retried, still on its way"
    );
    line.task().stop().unwrap();
    let outcome = analog_outcome(&card, 0, n);
    assert!(
        matches!(outcome, Some(Err(DeviceError::Undelivered { reason })) if reason.contains("line stopped")),
        "{outcome:?}"
    );
}

/// A write the unit answers with an exception is refused: it fails (Undelivered, naming
/// the exception), is not sent again, and the unit stays online; later writes go through.
#[test]
fn a_write_refused_with_an_exception_fails_and_is_not_resent() {
    let server = TestServer::start();
    server.memory().lock().unwrap().write_exception = Some(ExceptionCode::IllegalDataValue);
    let card = card(MODBUS_MAP);
    let (stats, _line) = line_with("mb-refused", &server, &card, timing(1));
    wait_until("online", || card.health().status == Status::Online);
    card.write(0, 99.0).unwrap();
    let n = analog_taken(&card, 0);
    let outcome = settled(&card, 0, n);
    assert!(
        matches!(&outcome, Err(DeviceError::Undelivered { reason }) if reason.contains("IllegalDataValue (0x03)")),
        "{outcome:?}"
    );
    // Several good polls later: sent once, counted once, never retried.
    let polls = stats.polls.load(Ordering::Relaxed);
    wait_until("five more polls", || {
        stats.polls.load(Ordering::Relaxed) >= polls + 5
    });
    assert_eq!(server.memory().lock().unwrap().writes, 1, "not resent");
    let c = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    assert_eq!(
        (
            c(&stats.exceptions),
            c(&stats.writes_failed),
            c(&stats.write_retries)
        ),
        (1, 1, 0)
    );
    assert_eq!(card.health().status, Status::Online);
    assert_eq!(server.memory().lock().unwrap().holding[10], 0);
    // The unit takes writes again: the next one is delivered.
    server.memory().lock().unwrap().write_exception = None;
    card.write(0, 100.0).unwrap();
    settled(&card, 0, analog_taken(&card, 0)).unwrap();
    assert_eq!(server.memory().lock().unwrap().holding[10], 100);
}

/// ServerDeviceBusy asks for a later try: the write is sent again, and delivered once the
/// unit takes it.
#[test]
fn a_write_answered_busy_is_sent_again() {
    let server = TestServer::start();
    server.memory().lock().unwrap().write_exception = Some(ExceptionCode::ServerDeviceBusy);
    let card = card(MODBUS_MAP);
    let t = UnitTiming {
        offline_after: u32::MAX,
        stale_after: u32::MAX,
        ..timing(1)
    };
    let (stats, _line) = line_with("mb-busy", &server, &card, t);
    wait_until("online", || card.health().status == Status::Online);
    card.write(0, 5.0).unwrap();
    let n = analog_taken(&card, 0);
    wait_until("sent three times", || {
        server.memory().lock().unwrap().writes >= 3
    });
    assert!(analog_outcome(&card, 0, n).is_none(), "still on its way");
    server.memory().lock().unwrap().write_exception = None;
    settled(&card, 0, n).unwrap();
    assert_eq!(server.memory().lock().unwrap().holding[10], 5);
    assert_eq!(stats.writes_failed.load(Ordering::Relaxed), 0);
    assert!(stats.write_retries.load(Ordering::Relaxed) >= 3);
}
