//! hwgw's Modbus TCP server loop: MBAP framing, every request checked by [`pdu`] before
//! the [`RegisterTable`] answers it, and the limits a server on a plant network needs.
//!
//! - At most `max_clients` connections at once. When they are all open, a new one is
//!   admitted by closing the connection idle longest — the one whose last complete request
//!   (or, without one, whose accept) is oldest — as the Modbus Messaging on TCP/IP
//!   Implementation Guide's connection management has it (counted as evicted): idle or
//!   half-open sockets cannot lock a master out, and the descriptors stay bounded. Bytes of
//!   a frame not yet complete do not count as activity.
//! - At most `max_clients_per_address` connections from one IP address; one more from it
//!   is closed at once (counted), so one device reopening sockets cannot take the table
//!   from the others — nor evict them.
//! - A connection quiet for `idle_timeout` is closed (counted); so is one that does not
//!   take its reply for as long (a client that sends and never reads cannot hold a slot).
//! - A frame begun must be whole within `frame_timeout` (shorter than `idle_timeout`) of
//!   its first bytes, or the connection is closed (counted): a half-sent MBAP header or
//!   body holds no slot for long.
//! - A frame whose MBAP header is not Modbus (protocol id ≠ 0, length outside 2–254) cannot
//!   be resynchronised on a stream: the connection is closed (counted as malformed).
//! - `accept` failing (out of descriptors: EMFILE/ENFILE, or any other error) is counted and
//!   retried after 10 ms, doubling up to 1 s: the loop never ends but at stop.
//! - A panic while answering (a device's bug) is caught, answered 04, counted and logged
//!   (not printed by the default panic hook).
//! - A write to a device whose bus carries it later (see [`server`](crate::server#writes-a-bus-carries-later))
//!   is answered once it is settled: delivered, the normal reply (counted as
//!   `writes_confirmed`); failed, 04 or 0x0B (`writes_failed`); still on its way after
//!   `write_confirm`, 0x0B (`writes_unconfirmed`). The connection's task waits (polling the
//!   delivery state in steps of 1 to 5 ms on tokio's timer), so the other connections are
//!   served meanwhile; that connection's next request is read after the reply.
//!
//! [`ServerCounters`] says all of it; [`ModbusServer::health`] is `Err` while the loop does
//! not run (stopped, or its thread ended by a panic) and while `accept` has failed without
//! a success for [`ACCEPT_FAILING_LIMIT`] — what the gateway's watchdog sees.

use crate::pdu::{self, Refusal, Resp, exception};
use crate::server::{Answer, ExceptionCode, RegisterTable, Unsettled};
use serde::Serialize;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

pub use crate::limits::{DEFAULT_WRITE_CONFIRM, Limits};

/// How long `accept` may fail without a success before the server is unhealthy.
pub const ACCEPT_FAILING_LIMIT: Duration = Duration::from_secs(5);

#[derive(Debug, Default)]
struct Stats {
    running: AtomicBool,
    /// When `accept` started failing (ns since `epoch`, plus 1), 0 while it succeeds.
    failing_since: AtomicU64,
    clients: AtomicUsize,
    connections: AtomicU64,
    evicted: AtomicU64,
    refused_per_address: AtomicU64,
    requests: AtomicU64,
    exceptions: AtomicU64,
    malformed: AtomicU64,
    idle_closed: AtomicU64,
    frame_timeouts: AtomicU64,
    accept_errors: AtomicU64,
    panics: AtomicU64,
    writes_confirmed: AtomicU64,
    writes_failed: AtomicU64,
    writes_unconfirmed: AtomicU64,
}

/// The server's state and counters.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ServerCounters {
    /// The accept loop runs.
    pub running: bool,
    /// Connections open now.
    pub clients: usize,
    /// Connections accepted and served.
    pub connections: u64,
    /// Connections closed to admit a new one while `max_clients` were open: each the one
    /// idle longest.
    pub evicted: u64,
    /// Connections closed at once: `max_clients_per_address` from their address were open.
    pub refused_per_address: u64,
    /// Requests read.
    pub requests: u64,
    /// Requests answered with an exception.
    pub exceptions: u64,
    /// Connections closed on a frame that is not Modbus TCP.
    pub malformed: u64,
    /// Connections closed after `idle_timeout` of silence, or of a reply not taken.
    pub idle_closed: u64,
    /// Connections closed on a frame begun and not whole within `frame_timeout`.
    pub frame_timeouts: u64,
    /// Failed `accept` calls (e.g. out of descriptors), each retried after a backoff.
    pub accept_errors: u64,
    /// Panics caught while answering.
    pub panics: u64,
    /// Write requests answered after their device's bus delivered the writes (those to
    /// devices that apply a write within the call are not counted).
    pub writes_confirmed: u64,
    /// Write requests answered 04 or 0x0B because their device's bus failed a write.
    pub writes_failed: u64,
    /// Write requests answered 0x0B because a write was still on its way after
    /// `write_confirm`.
    pub writes_unconfirmed: u64,
}

fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// A running server; dropping it stops it and closes its clients' connections.
pub struct ModbusServer {
    addr: SocketAddr,
    stats: Arc<Stats>,
    epoch: std::time::Instant,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ModbusServer {
    /// Serves `table` on `listen` from a thread of its own, within `limits`.
    pub fn start(
        listen: SocketAddr,
        table: RegisterTable,
        limits: Limits,
    ) -> std::io::Result<ModbusServer> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let listener = rt.block_on(tokio::net::TcpListener::bind(listen))?;
        let addr = listener.local_addr()?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let stats = Arc::new(Stats::default());
        stats.running.store(true, Ordering::Release);
        quiet_panics();
        let epoch = std::time::Instant::now();
        let (table, s) = (Arc::new(table), stats.clone());
        let thread = std::thread::Builder::new()
            .name(SERVER_THREAD.into())
            .spawn(move || {
                // Not running once this thread ends, however it ends (a panic too).
                let _running = Running(s.clone());
                rt.block_on(accept_loop(listener, table, s, limits, rx, epoch));
                // Dropping the runtime here cancels every connection's task.
            })?;
        tracing::info!("modbus server listening on {addr}");
        Ok(ModbusServer {
            addr,
            stats,
            epoch,
            stop: Some(tx),
            thread: Some(thread),
        })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Its state and counters now.
    pub fn counters(&self) -> ServerCounters {
        let s = &self.stats;
        let n = |c: &AtomicU64| c.load(Ordering::Relaxed);
        ServerCounters {
            running: s.running.load(Ordering::Acquire),
            clients: s.clients.load(Ordering::Relaxed),
            connections: n(&s.connections),
            evicted: n(&s.evicted),
            refused_per_address: n(&s.refused_per_address),
            requests: n(&s.requests),
            exceptions: n(&s.exceptions),
            malformed: n(&s.malformed),
            idle_closed: n(&s.idle_closed),
            frame_timeouts: n(&s.frame_timeouts),
            accept_errors: n(&s.accept_errors),
            panics: n(&s.panics),
            writes_confirmed: n(&s.writes_confirmed),
            writes_failed: n(&s.writes_failed),
            writes_unconfirmed: n(&s.writes_unconfirmed),
        }
    }

    /// `Ok` while the accept loop runs and accepts: `Err` once it stopped, or while
    /// `accept` has failed for [`ACCEPT_FAILING_LIMIT`] without a success.
    pub fn health(&self) -> Result<(), ServerFault> {
        let addr = self.addr;
        if !self.stats.running.load(Ordering::Acquire) {
            return Err(ServerFault::Stopped { addr });
        }
        let since = self.stats.failing_since.load(Ordering::Acquire);
        if since != 0 {
            let now = self.epoch.elapsed().as_nanos() as u64;
            let failing = Duration::from_nanos(now.saturating_sub(since - 1));
            if failing >= ACCEPT_FAILING_LIMIT {
                let failures = self.stats.accept_errors.load(Ordering::Relaxed);
                return Err(ServerFault::AcceptFailing {
                    addr,
                    failing,
                    failures,
                });
            }
        }
        Ok(())
    }
}

/// Why a running [`ModbusServer`] does not serve as it should.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ServerFault {
    /// Its loop does not run (stopped, or its thread ended by a panic).
    #[error("the modbus server on {addr} has stopped")]
    Stopped {
        /// Where it listened.
        addr: SocketAddr,
    },
    /// `accept` has failed without a success this long.
    #[error(
        "the modbus server on {addr} has accepted no connection for {:.1} s: accept fails ({failures} failures; out of file descriptors?)",
        failing.as_secs_f64()
    )]
    AcceptFailing {
        /// Where it listens.
        addr: SocketAddr,
        /// How long accept has failed.
        failing: Duration,
        /// Accept errors counted.
        failures: u64,
    },
}

/// The server thread's name (its panics are logged, not printed: see [`quiet_panics`]).
const SERVER_THREAD: &str = "modbus-server";

/// Marks the server stopped when dropped (its thread's end, a panic included).
struct Running(Arc<Stats>);

impl Drop for Running {
    fn drop(&mut self) {
        self.0.running.store(false, Ordering::Release);
    }
}

/// Installs, once, a panic hook that logs a panic on the server's thread through tracing
/// (where it is caught and answered 04) and hands every other panic to the hook that was
/// there before.
fn quiet_panics() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if std::thread::current().name() == Some(SERVER_THREAD) {
                tracing::error!("modbus server: a device panicked while answering: {info}");
            } else {
                previous(info);
            }
        }));
    });
}

impl Drop for ModbusServer {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A connection being served, as the accept loop keeps it.
struct Slot {
    /// Its peer's address (an IPv4-mapped IPv6 address as IPv4).
    ip: IpAddr,
    /// When it last completed a request (its accept, before it did): ns since `epoch`.
    last: Arc<AtomicU64>,
    task: tokio::task::JoinHandle<()>,
}

/// Counts a connection open from its spawn to its end, however it ends (an eviction's
/// abort too).
struct Open(Arc<Stats>);

impl Drop for Open {
    fn drop(&mut self) {
        self.0.clients.fetch_sub(1, Ordering::AcqRel);
    }
}

/// What the accept loop does with a new connection.
enum Admit {
    /// Serve it.
    Take,
    /// Close `slots[i]`, the one idle longest (every slot is taken), and serve it.
    Evict(usize),
    /// Close it at once: its address has its share.
    Refuse,
}

/// What to do with a new connection from `ip`, given those open (`slots`, finished ones
/// already dropped).
fn admit(slots: &[Slot], ip: IpAddr, limits: &Limits) -> Admit {
    if slots.iter().filter(|s| s.ip == ip).count() >= limits.max_clients_per_address {
        return Admit::Refuse;
    }
    if slots.len() < limits.max_clients {
        return Admit::Take;
    }
    // The oldest last complete request; on a tie the earliest accepted.
    (0..slots.len())
        .min_by_key(|&i| slots[i].last.load(Ordering::Relaxed))
        .map_or(Admit::Take, Admit::Evict)
}

fn since(epoch: std::time::Instant) -> u64 {
    epoch.elapsed().as_nanos() as u64
}

async fn accept_loop(
    listener: tokio::net::TcpListener,
    table: Arc<RegisterTable>,
    stats: Arc<Stats>,
    limits: Limits,
    mut stop: tokio::sync::oneshot::Receiver<()>,
    epoch: std::time::Instant,
) {
    const FIRST: Duration = Duration::from_millis(10);
    let mut backoff = FIRST;
    let mut slots: Vec<Slot> = Vec::with_capacity(limits.max_clients);
    loop {
        let accepted = tokio::select! {
            _ = &mut stop => return,
            a = listener.accept() => a,
        };
        match accepted {
            Ok((stream, peer)) => {
                backoff = FIRST;
                stats.failing_since.store(0, Ordering::Release);
                slots.retain(|s| !s.task.is_finished());
                let ip = peer.ip().to_canonical();
                match admit(&slots, ip, &limits) {
                    Admit::Refuse => {
                        if first_of_hundred(&stats.refused_per_address) {
                            tracing::warn!(
                                "modbus server: {peer} refused: {} connections from {ip} are open (max_clients_per_address)",
                                limits.max_clients_per_address
                            );
                        }
                        drop(stream);
                        continue;
                    }
                    Admit::Evict(i) => {
                        // Its task ends (and its socket closes) at its next turn; its
                        // slot is free now.
                        let victim = slots.remove(i);
                        victim.task.abort();
                        let idle = Duration::from_nanos(
                            since(epoch).saturating_sub(victim.last.load(Ordering::Relaxed)),
                        );
                        if first_of_hundred(&stats.evicted) {
                            tracing::info!(
                                "modbus server: {} connections open: closed one from {} idle for {:.1} s to admit {peer}",
                                limits.max_clients,
                                victim.ip,
                                idle.as_secs_f64()
                            );
                        }
                    }
                    Admit::Take => {}
                }
                stats.clients.fetch_add(1, Ordering::AcqRel);
                bump(&stats.connections);
                let last = Arc::new(AtomicU64::new(since(epoch)));
                let open = Open(stats.clone());
                let (table, stats, at) = (table.clone(), stats.clone(), last.clone());
                let task = tokio::spawn(async move {
                    let _open = open;
                    let _ = stream.set_nodelay(true);
                    let conn = Conn {
                        table: &table,
                        stats: &stats,
                        limits,
                        last: &at,
                        epoch,
                    };
                    if let Err(e) = conn.serve(stream).await {
                        tracing::debug!("modbus server: {peer}: {e}");
                    }
                });
                slots.push(Slot { ip, last, task });
            }
            Err(e) => {
                let now = since(epoch) + 1;
                let _ = stats.failing_since.compare_exchange(
                    0,
                    now,
                    Ordering::AcqRel,
                    Ordering::Relaxed,
                );
                if first_of_hundred(&stats.accept_errors) {
                    tracing::warn!("modbus server: accept: {e} (retrying in {backoff:?})");
                }
                tokio::select! {
                    _ = &mut stop => return,
                    _ = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(Duration::from_secs(1));
            }
        }
    }
}

/// One connection's context.
struct Conn<'a> {
    table: &'a RegisterTable,
    stats: &'a Stats,
    limits: Limits,
    /// Set to `since(epoch)` at each complete request.
    last: &'a AtomicU64,
    epoch: std::time::Instant,
}

impl Conn<'_> {
    /// Serves one connection until the client closes it, it idles out, stops mid-frame or
    /// sends no Modbus.
    async fn serve(&self, mut stream: tokio::net::TcpStream) -> std::io::Result<()> {
        let (stats, idle) = (self.stats, self.limits.idle_timeout);
        let frame = self.limits.frame_timeout.min(idle);
        let mut head = [0u8; 7];
        let mut body = [0u8; 253];
        let mut out = Vec::with_capacity(260);
        loop {
            // A frame's first bytes, for up to `idle`; the rest of it within `frame` of them.
            let got = match tokio::time::timeout(idle, stream.read(&mut head)).await {
                Err(_) => {
                    bump(&stats.idle_closed);
                    return Ok(());
                }
                Ok(Ok(0)) => return Ok(()),
                Ok(r) => r?,
            };
            let deadline = tokio::time::Instant::now() + frame;
            if got < head.len() {
                match tokio::time::timeout_at(deadline, stream.read_exact(&mut head[got..])).await {
                    Err(_) => {
                        bump(&stats.frame_timeouts);
                        return Ok(());
                    }
                    Ok(Err(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(()),
                    Ok(r) => r?,
                };
            }
            // The transaction id (head[0..2]) is echoed as it came.
            let (pid, len, unit) = (
                u16::from_be_bytes([head[2], head[3]]),
                usize::from(u16::from_be_bytes([head[4], head[5]])),
                head[6],
            );
            if pid != 0 || !(2..=254).contains(&len) {
                bump(&stats.malformed);
                return Ok(());
            }
            let pdu = &mut body[..len - 1];
            match tokio::time::timeout_at(deadline, stream.read_exact(pdu)).await {
                Err(_) => {
                    bump(&stats.frame_timeouts);
                    return Ok(());
                }
                Ok(r) => r?,
            };
            // A complete request: this connection is not idle (eviction goes by this).
            self.last.store(since(self.epoch), Ordering::Relaxed);
            bump(&stats.requests);
            let function = pdu[0];
            let answer = match take(self.table, stats, pdu) {
                Ok(Answer { reply, unsettled }) if !unsettled.is_empty() => {
                    // Awaited here, in this connection's task: the others are served
                    // meanwhile.
                    self.settle(unsettled)
                        .await
                        .map(|()| reply)
                        .map_err(|code| Refusal { function, code })
                }
                other => other.map(|a| a.reply),
            };
            out.clear();
            out.extend_from_slice(&[head[0], head[1], 0, 0, 0, 0, unit]);
            encode(stats, answer, &mut out);
            let n = (out.len() - 6) as u16;
            out[4..6].copy_from_slice(&n.to_be_bytes());
            match tokio::time::timeout(idle, stream.write_all(&out)).await {
                Err(_) => {
                    // The client does not take its replies.
                    bump(&stats.idle_closed);
                    return Ok(());
                }
                Ok(r) => r?,
            }
        }
    }
}

impl Conn<'_> {
    /// Waits until the writes of a request are settled, at most `write_confirm`: `Ok` once
    /// every one is delivered, else the exception answering the request (see
    /// [`server::undelivered`](crate::server::undelivered)). Counts the outcome.
    async fn settle(&self, mut writes: Unsettled) -> Result<(), ExceptionCode> {
        const FIRST: Duration = Duration::from_millis(1);
        const MOST: Duration = Duration::from_millis(5);
        let stats = self.stats;
        let deadline = tokio::time::Instant::now() + self.limits.write_confirm;
        let mut pause = FIRST;
        loop {
            let Ok(now) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| writes.check()))
            else {
                // A device's bug, as a panic while answering.
                bump(&stats.panics);
                return Err(exception::SERVER_DEVICE_FAILURE);
            };
            match now {
                Some(Ok(())) => {
                    bump(&stats.writes_confirmed);
                    return Ok(());
                }
                Some(Err(why)) => {
                    if first_of_hundred(&stats.writes_failed) {
                        tracing::warn!("modbus server: a write was not delivered: {why}");
                    }
                    return Err(crate::server::undelivered(&why));
                }
                None if tokio::time::Instant::now() >= deadline => {
                    if first_of_hundred(&stats.writes_unconfirmed) {
                        tracing::warn!(
                            "modbus server: {} write(s) still on their way after {:?} (write_confirm_ms): answered 0x0B",
                            writes.len(),
                            self.limits.write_confirm
                        );
                    }
                    return Err(exception::GATEWAY_TARGET_FAILED_TO_RESPOND);
                }
                None => {
                    tokio::time::sleep_until(deadline.min(tokio::time::Instant::now() + pause))
                        .await;
                    pause = (pause * 2).min(MOST);
                }
            }
        }
    }
}

/// Checks `pdu` and has the table answer it (its writes made): the reply and the writes
/// it waits for, or the refusal.
fn take(table: &RegisterTable, stats: &Stats, pdu: &[u8]) -> Result<Answer, Refusal> {
    pdu::parse(pdu).and_then(|req| {
        let function = pdu[0];
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| table.answer(req)))
            .unwrap_or_else(|_| {
                bump(&stats.panics);
                Err(exception::SERVER_DEVICE_FAILURE)
            })
            .map_err(|code| Refusal { function, code })
    })
}

/// Appends the reply PDU (or the exception) to `out`.
fn encode(stats: &Stats, answer: Result<Resp, Refusal>, out: &mut Vec<u8>) {
    match answer {
        Ok(resp) => pdu::encode(&resp, out),
        Err(r) => {
            bump(&stats.exceptions);
            pdu::encode_refusal(r, out);
        }
    }
}

/// Answers `pdu` as the server would, into `out` (for tests and the fuzz run: the whole
/// request path but the socket) — except that it does not wait for writes a device's bus
/// carries later: it answers as if they were delivered.
pub fn answer_pdu(table: &RegisterTable, pdu: &[u8], out: &mut Vec<u8>) {
    thread_local! {
        static STATS: Stats = Stats::default();
    }
    STATS.with(|s| encode(s, take(table, s, pdu).map(|a| a.reply), out));
}

/// Counts one more on `counter`; true for the first of every hundred (what is logged, so a
/// flood is counted in full but said only now and then).
fn first_of_hundred(counter: &AtomicU64) -> bool {
    counter.fetch_add(1, Ordering::Relaxed).is_multiple_of(100)
}
