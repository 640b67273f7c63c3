//! hwgw's Modbus server: its TCP loops (Modbus TCP, and RTU frames over TCP; see
//! [`framing`](crate::framing)), its serial port ([`slave`](crate::slave)), every request
//! checked by [`pdu`](crate::pdu) before the [`RegisterTable`] answers it
//! ([`conn`](crate::conn)), and the limits a server on a plant network needs (per TCP
//! listener).
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

use crate::conn::Conn;
use crate::framing::Framing;
use crate::server::RegisterTable;
use crate::shared::{Shared, Stats, Units, bump, first_of_hundred};
use crate::slave::SerialSlave;
use serde::Serialize;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

pub use crate::conn::answer_pdu;
pub use crate::limits::{DEFAULT_WRITE_CONFIRM, Limits};

/// How long `accept` may fail without a success before the server is unhealthy.
pub const ACCEPT_FAILING_LIMIT: Duration = Duration::from_secs(5);

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
    /// Connections closed on an MBAP frame begun and not whole within `frame_timeout`;
    /// partial RTU frames dropped (after a pause on a serial line, `frame_timeout` on TCP).
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
    /// Runs of RTU bytes that are no frame (a bad CRC, noise), dropped until a good frame.
    pub crc_errors: u64,
    /// RTU broadcasts (unit 0) taken: their writes applied, not answered.
    pub broadcasts: u64,
    /// RTU frames of other units on the line (requests for them, their replies), skipped.
    pub other_units: u64,
    /// TCP requests for a unit the server has no route to, answered 0x0A.
    pub unreachable: u64,
    /// Requests forwarded to a line and answered by their target (its exceptions too).
    pub forwarded: u64,
    /// Forwarded requests answered 0x0B: no reply from the target within the timeout.
    pub gateway_no_response: u64,
    /// Forwarded requests answered 0x0A: the line's queue full, the line stopped or
    /// broken.
    pub gateway_unavailable: u64,
    /// Times the serial port was opened (the RTU slave; 0 without one).
    pub port_opens: u64,
    /// Failures to open or set up the serial port, and errors that closed it.
    pub port_errors: u64,
}

/// Where a server serves, and as which units.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Endpoints {
    /// Modbus TCP (MBAP) on this address.
    pub tcp: Option<SocketAddr>,
    /// RTU frames over TCP on this address (a serial device server's way).
    pub rtu_over_tcp: Option<SocketAddr>,
    /// An RTU slave on this serial port.
    pub serial: Option<SerialSlave>,
    /// The unit ids it answers as its own (see [`conn`](crate::conn)).
    pub units: Units,
    /// Where requests for other units go (gateway mode; see [`gateway`](crate::gateway)),
    /// the first route that takes a unit.
    pub gateway: Vec<crate::gateway::Route>,
}

impl Endpoints {
    /// Where, for messages and status: "127.0.0.1:502, rtu_over_tcp 127.0.0.1:5020, rtu
    /// /dev/ttyS1" (Modbus TCP's address alone, as a server of Modbus TCP only shows it).
    pub fn describe(&self) -> String {
        let mut v = Vec::new();
        if let Some(a) = self.tcp {
            v.push(a.to_string());
        }
        if let Some(a) = self.rtu_over_tcp {
            v.push(format!("rtu_over_tcp {a}"));
        }
        if let Some(s) = &self.serial {
            v.push(format!("rtu {}", s.serial.device.display()));
        }
        v.join(", ")
    }
}

/// A running server; dropping it stops it and closes its clients' connections.
pub struct ModbusServer {
    /// Where it serves, the ports bound.
    bound: Endpoints,
    stats: Arc<Stats>,
    epoch: std::time::Instant,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ModbusServer {
    /// Serves `table` over Modbus TCP on `listen`, every unit id, from a thread of its
    /// own, within `limits`.
    pub fn start(
        listen: SocketAddr,
        table: RegisterTable,
        limits: Limits,
    ) -> std::io::Result<ModbusServer> {
        let at = Endpoints {
            tcp: Some(listen),
            ..Endpoints::default()
        };
        ModbusServer::serve(at, table, limits)
    }

    /// Serves `table` at `endpoints` from a thread of its own, within `limits`. The TCP
    /// listeners are bound now (an error if one cannot be); the serial port is opened on
    /// the thread, and opened again after a failure (see [`slave`](crate::slave)).
    pub fn serve(
        endpoints: Endpoints,
        table: RegisterTable,
        limits: Limits,
    ) -> std::io::Result<ModbusServer> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let bind = |at: Option<SocketAddr>| -> std::io::Result<_> {
            at.map(|a| rt.block_on(tokio::net::TcpListener::bind(a)))
                .transpose()
        };
        let (tcp, rtu) = (bind(endpoints.tcp)?, bind(endpoints.rtu_over_tcp)?);
        let local =
            |l: &Option<tokio::net::TcpListener>| l.as_ref().map(|l| l.local_addr()).transpose();
        let (addr, rtu_addr) = (local(&tcp)?, local(&rtu)?);
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let stats = Arc::new(Stats::default());
        stats.running.store(true, Ordering::Release);
        quiet_panics();
        let epoch = std::time::Instant::now();
        let bound = Endpoints {
            tcp: addr,
            rtu_over_tcp: rtu_addr,
            ..endpoints.clone()
        };
        let shared = Arc::new(Shared {
            table,
            stats: stats.clone(),
            limits,
            units: endpoints.units.clone(),
            routes: endpoints.gateway.clone(),
            epoch,
        });
        let slave = endpoints.serial;
        let thread = std::thread::Builder::new()
            .name(SERVER_THREAD.into())
            .spawn(move || {
                // Not running once this thread ends, however it ends (a panic too).
                let _running = Running(shared.stats.clone());
                let gap = crate::framing::rtu_gap(None);
                let all = async {
                    tokio::join!(
                        async {
                            if let Some(l) = tcp {
                                accept_loop(l, shared.clone(), Framing::Mbap).await
                            }
                        },
                        async {
                            if let Some(l) = rtu {
                                accept_loop(l, shared.clone(), Framing::Rtu { gap, tcp: true })
                                    .await
                            }
                        },
                        async {
                            if let Some(s) = slave {
                                crate::slave::serve(s, shared.clone()).await
                            }
                        },
                    )
                };
                rt.block_on(async {
                    tokio::select! {
                        _ = rx => {}
                        _ = all => {}
                    }
                });
                // Dropping the runtime here cancels every connection's task.
            })?;
        for (what, at) in [("Modbus TCP", addr), ("RTU over TCP", rtu_addr)] {
            if let Some(a) = at {
                tracing::info!("modbus server: {what} on {a}");
            }
        }
        Ok(ModbusServer {
            bound,
            stats,
            epoch,
            stop: Some(tx),
            thread: Some(thread),
        })
    }

    /// Where it listens for Modbus TCP (else for RTU over TCP; else 0.0.0.0:0, a server
    /// on a serial port only).
    pub fn addr(&self) -> SocketAddr {
        self.bound
            .tcp
            .or(self.bound.rtu_over_tcp)
            .unwrap_or(SocketAddr::from(([0, 0, 0, 0], 0)))
    }

    /// Where it listens for RTU frames over TCP.
    pub fn rtu_addr(&self) -> Option<SocketAddr> {
        self.bound.rtu_over_tcp
    }

    /// Everywhere it serves, for messages: "127.0.0.1:502, rtu_over_tcp …, rtu
    /// /dev/ttyS1" (with the ports bound; see [`Endpoints::describe`]).
    pub fn describe(&self) -> String {
        self.bound.describe()
    }

    /// Where it serves, the ports bound.
    pub fn endpoints(&self) -> &Endpoints {
        &self.bound
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
            crc_errors: n(&s.crc_errors),
            broadcasts: n(&s.broadcasts),
            other_units: n(&s.other_units),
            unreachable: n(&s.unreachable),
            forwarded: n(&s.forwarded),
            gateway_no_response: n(&s.gateway_no_response),
            gateway_unavailable: n(&s.gateway_unavailable),
            port_opens: n(&s.port.opens),
            port_errors: n(&s.port.errors),
        }
    }

    /// `Ok` while the accept loop runs and accepts: `Err` once it stopped, or while
    /// `accept` has failed for [`ACCEPT_FAILING_LIMIT`] without a success.
    pub fn health(&self) -> Result<(), ServerFault> {
        let addr = self.describe();
        if !self.stats.running.load(Ordering::Acquire) {
            return Err(ServerFault::Stopped { addr });
        }
        if let Some(device) = self.bound.serial.as_ref().map(|s| &s.serial.device)
            && let Some((failing, error)) = self.stats.port.failing(self.epoch)
            && failing >= ACCEPT_FAILING_LIMIT
        {
            return Err(ServerFault::Port {
                device: device.clone(),
                failing,
                error,
            });
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
        /// Where it served ([`ModbusServer::describe`]).
        addr: String,
    },
    /// Its serial port has not served for this long.
    #[error(
        "the modbus server's serial port {} has not served for {:.1} s: {error}",
        device.display(),
        failing.as_secs_f64()
    )]
    Port {
        /// The port.
        device: std::path::PathBuf,
        /// How long it has failed.
        failing: Duration,
        /// The last error.
        error: String,
    },
    /// `accept` has failed without a success this long.
    #[error(
        "the modbus server on {addr} has accepted no connection for {:.1} s: accept fails ({failures} failures; out of file descriptors?)",
        failing.as_secs_f64()
    )]
    AcceptFailing {
        /// Where it listens.
        addr: String,
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

/// Accepts connections on `listener` and serves each in a task of its own, `framing` on
/// all of them, until dropped.
async fn accept_loop(listener: tokio::net::TcpListener, shared: Arc<Shared>, framing: Framing) {
    let (stats, limits, epoch) = (&shared.stats, shared.limits, shared.epoch);
    const FIRST: Duration = Duration::from_millis(10);
    let mut backoff = FIRST;
    let mut slots: Vec<Slot> = Vec::with_capacity(limits.max_clients);
    loop {
        match listener.accept().await {
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
                let (shared, at) = (shared.clone(), last.clone());
                let task = tokio::spawn(async move {
                    let _open = open;
                    let mut stream = stream;
                    let _ = stream.set_nodelay(true);
                    let conn = Conn {
                        table: &shared.table,
                        stats: &shared.stats,
                        limits: shared.limits,
                        units: &shared.units,
                        routes: &shared.routes,
                        framing,
                        reply_delay: Duration::ZERO,
                        idle_close: true,
                        echo: false,
                        last: &at,
                        epoch: shared.epoch,
                    };
                    if let Err(e) = conn.serve(&mut stream).await {
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
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(1));
            }
        }
    }
}
