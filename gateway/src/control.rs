//! The control socket: line-delimited JSON over a Unix domain socket, typed by
//! [`crate::protocol`].
//!
//! Each request is one JSON object on one line with an `id` (echoed back) and a `cmd`;
//! each reply is one line: `{"id": …, "ok": …}` or `{"id": …, "error": {"kind": …,
//! "message": …}}`. A malformed, unknown or oversized request gets an error reply and the
//! connection stays open; every client has its own thread, so a slow one delays nobody.
//! The server takes a bounded number of clients (`busy` beyond), closes a client that
//! sends nothing for the idle timeout, and backs off when the process is out of file
//! descriptors rather than spinning. Where the socket goes and who may use it:
//! [`crate::socket`].
//!
//! | cmd | fields | ok |
//! |---|---|---|
//! | `ls` | optional `all` | `[{"name", "state"}]` of every component; with `all`, of every gateway's, named `gateway/component` |
//! | `describe` | `component` | ports, operations, properties, attributes, state, counters, activity statistics |
//! | `devices` | — | every registry name: interface, name, owner, alias_of |
//! | `status` | — | health, every device's health, every card's bus counters, every component's state and timing |
//! | `get` | `component` and `port` or `property` | an output port's last value, an input port's read-back (a device output) or last value read, or the property's value |
//! | `set` | `component`, `port` or `property`, `value` | `null`; a port must be an input port |
//! | `call` | `component`, `operation`, `args` (array) | the result |
//! | `configure` | `component` | the new state |
//! | `start` | `component` | the new state |
//! | `stop` | `component` | the new state |
//! | `cleanup` | `component` | the new state |
//! | `recover` | `component` | the new state |
//! | `watch` | `component`, `port`, optional `count` | `"watching"`, then a stream: one `{"id", "event": {"status", "value"}}` line per new value (all of them, `count` at most), and `{"id", "heartbeat": ns}` after each second without one, until the client closes |
//! | `record` | `ports` (`component.port` or `component`), optional `devices`, `steps`, `buffer` | `{"ports", "activities", "wall_minus_clock_ns"}`, then a stream of `{"id", "records": {"items", "ports_lost", "steps_lost", "now_ns"}}` batches until the client closes |
//! | `reload` | — | `{"applied", "restart", "errors"}`: the deployment file read again and what changed rebuilt; when the new deployment has errors they are listed and nothing changed |
//! | `load` | `component`: a `[[component]]` table as JSON (`name`, `type`, `activity`, optional `properties`, `start`, `requires`) | the reload's report: the component built, configured and started as the deployment file's are; with an error, nothing changed and the error lists why |
//! | `unload` | `component` | the reload's report: the component stopped, cleaned up and removed, its connections closed |
//! | `connect` | `from`, `to` (`component.port`), optional `policy` (as in a `[[connection]]`) | `{"id", "applied"}`: the new connection's id |
//! | `disconnect` | `connection`: its id | the reload's report: the connection closed |
//! | `set_period` | `component`, `period_ms` | `null`: the stopped component's periodic activity takes the period at its next start |
//! | `set_priority` | `component`, `policy` (`"other"`, `"fifo"`), `priority` | `null`: the stopped component's thread takes them at its next start |
//! | `properties` | `component` | its properties as TOML text (what `save-properties` writes) |
//! | `load_properties` | `component`, `properties` (an object of property names, nested for bags) | `null`: every value set, or none when one is refused |
//! | `changes` | — | the run-time changes (load, unload, connect, disconnect) since the deployment file was read, a line each |
//! | `deployment` | — | the running deployment as TOML text: the file's with the run-time changes |
//! | `log` | optional `component`, optional `level` (`off`, `error`, `warn`, `info`, `debug`, `trace`) | `{"areas": [{"name", "level"}], "counters": {"written", "dropped", "queued"}}`: the real-time log's levels (`component`'s only when given), after setting `component`'s to `level` |
//!
//! A request naming a component `<gateway>/<component>` that is not one of this gateway's
//! is carried out by that gateway, through Zenoh (see [`crate::forward`]).
//!
//! Error kinds: `parse`, `too_long`, `bad_request`, `unknown_command`, `not_found`,
//! `failed`, `busy` (too many clients), `stopping` (the gateway is stopping: no request is
//! carried out once its outputs are going to their safe values).
//!
//! ```text
//! $ echo '{"id":1,"cmd":"get","component":"sim0.ai","port":"ch3"}' | socat - UNIX:/run/hwgw/hwgw.sock
//! {"id":1,"ok":2.4998}
//! ```

use crate::deploy::Gateway;
use crate::protocol::{Body, ErrorKind, Event, Reply, Request};
use crate::requests::{Fail, failed, handle, not_found};
use crate::socket::{Bound, SocketError};
use rtt::component::DynWriter;
use rtt::port::ConnPolicy;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::os::fd::AsFd;
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

/// Longest request line accepted, bytes.
pub const MAX_LINE: usize = 64 * 1024;

/// How many clients the server takes at once, and how long one may stay silent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Clients connected at once (each is a thread and a file descriptor).
    pub clients: usize,
    /// A client that sends nothing this long is disconnected (a watch is not idle).
    pub idle: Duration,
}

impl Limits {
    /// The limits a deployment sets (`control_clients`, `control_idle_s`; checked when
    /// it is built), the defaults for the rest.
    pub fn of(d: &crate::config::Deployment) -> Limits {
        let def = Limits::default();
        Limits {
            clients: d.control_clients.map_or(def.clients, |n| n as usize),
            idle: d
                .control_idle_s
                .and_then(|s| Duration::try_from_secs_f64(s).ok())
                .unwrap_or(def.idle),
        }
    }
}

/// Descriptors one client costs: its socket, and the second handle the server keeps to
/// disconnect it at close.
pub const FDS_PER_CLIENT: u64 = 2;

/// Descriptors kept for the rest of the gateway: cards' buses, Zenoh's sockets, files,
/// the listener itself.
pub const FDS_RESERVED: u64 = 256;

impl Limits {
    /// These limits within the process's file descriptor limit (`RLIMIT_NOFILE`, systemd's
    /// `LimitNOFILE`): when `clients` × [`FDS_PER_CLIENT`] + [`FDS_RESERVED`] is more
    /// than the soft limit, the soft limit is raised towards the hard one; when even that
    /// is too few, fewer clients are taken, and the log says so with both numbers — a
    /// gateway never promises clients it has no descriptors for.
    pub fn fit_descriptors(self) -> Limits {
        use nix::sys::resource::{Resource, getrlimit, setrlimit};
        let need = self.clients as u64 * FDS_PER_CLIENT + FDS_RESERVED;
        let Ok((soft, hard)) = getrlimit(Resource::RLIMIT_NOFILE) else {
            return self;
        };
        if need <= soft {
            return self;
        }
        let raised = need.min(hard);
        let have = match setrlimit(Resource::RLIMIT_NOFILE, raised, hard) {
            Ok(()) => raised,
            Err(_) => soft,
        };
        if need <= have {
            tracing::info!(
                "control_clients = {}: raised the file descriptor limit from {soft} to {have}",
                self.clients
            );
            return self;
        }
        let clients = (have.saturating_sub(FDS_RESERVED) / FDS_PER_CLIENT).max(1) as usize;
        tracing::warn!(
            "control_clients = {} needs {need} file descriptors ({FDS_PER_CLIENT} a client and \
             {FDS_RESERVED} for the rest); the limit is {have} (LimitNOFILE, hard {hard}): taking \
             {clients} clients at once",
            self.clients
        );
        Limits { clients, ..self }
    }
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            clients: 64,
            idle: Duration::from_secs(600),
        }
    }
}

/// Counters of the control server.
#[derive(Debug, Default)]
pub struct ControlStats {
    /// Clients accepted.
    pub clients: AtomicU64,
    /// Clients turned away for the client limit.
    pub refused: AtomicU64,
    /// Clients disconnected for staying silent.
    pub idle_closed: AtomicU64,
    /// Requests answered.
    pub requests: AtomicU64,
    /// Requests answered with an error.
    pub errors: AtomicU64,
    /// Requests being carried out now.
    pub under_way: AtomicU64,
    /// Clients that could not be taken for want of file descriptors, memory or threads
    /// (at accept, or just after: told so when that is possible).
    pub accept_failures: AtomicU64,
}

/// What the accept loop and the clients share.
struct Shared {
    gw: Arc<Gateway>,
    stats: ControlStats,
    limits: Limits,
    /// Set when the server closes: no request is carried out after it.
    closing: AtomicBool,
    /// Held shared by every request being carried out; [`ControlServer::close`] takes it
    /// exclusively, so it returns only once none is left.
    gate: RwLock<()>,
    /// The connected clients, to disconnect them at close.
    clients: Mutex<HashMap<u64, UnixStream>>,
    next_id: AtomicU64,
    /// `record` streams under way (at most [`MAX_RECORD_STREAMS`]).
    records: std::sync::atomic::AtomicUsize,
    /// Set by [`ControlServer::open`]: the gateway's servers are answered from then on.
    serving: AtomicBool,
    /// The writers the gateway's servers set input ports through, one per port as a
    /// socket client keeps them (a writer per request would leave a connection behind
    /// each), with the reload generation they were made in.
    server_writers: Mutex<(u64, Writers)>,
}

/// Writers into input ports by (component, port).
type Writers = HashMap<(String, String), Box<dyn DynWriter>>;

/// Lets go of `writers` when a reload has made ports again since `generation` (which
/// becomes the gateway's now).
fn drop_stale(gw: &Gateway, generation: &mut u64, writers: &mut Writers) {
    let now = gw.generation.load(Ordering::Acquire);
    if std::mem::replace(generation, now) != now {
        writers.clear();
    }
}

/// The most `record` streams at once: each holds buffers on the recorded ports and adds a
/// copy to each of their writes.
pub const MAX_RECORD_STREAMS: usize = 4;

/// How long a `record` batch may wait for its client to read.
const RECORD_WRITE_TIMEOUT: Duration = Duration::from_secs(10);

impl Shared {
    /// The counters, for `status`.
    fn report(&self) -> crate::protocol::ControlReport {
        let s = &self.stats;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        crate::protocol::ControlReport {
            connected: rtt::lock(&self.clients).len() as u64,
            clients: load(&s.clients),
            refused: load(&s.refused),
            idle_closed: load(&s.idle_closed),
            requests: load(&s.requests),
            errors: load(&s.errors),
            under_way: load(&s.under_way),
            accept_failures: load(&s.accept_failures),
        }
    }
}

/// How long [`ControlServer::close`] lets the requests under way finish.
pub const CLOSE_WAIT: Duration = Duration::from_secs(2);

/// The running control server; [`close`](ControlServer::close) (or dropping it) stops
/// accepting, waits for the requests under way, disconnects every client and removes the
/// socket it made.
pub struct ControlServer {
    bound: Bound,
    shared: Arc<Shared>,
    /// The listener until [`open`](ControlServer::open) hands it to the accept thread.
    listener: Option<std::os::unix::net::UnixListener>,
    accept: Option<std::thread::JoinHandle<()>>,
}

impl ControlServer {
    /// Binds `path` safely (see [`crate::socket::bind`]) to serve `gateway` on it within
    /// `limits`, once [`open`](Self::open) is called: until then a client connects and its
    /// request waits (so no request sees a gateway that has not started).
    pub fn start(
        gateway: Arc<Gateway>,
        path: &Path,
        limits: Limits,
    ) -> Result<ControlServer, SocketError> {
        let bound = crate::socket::bind(path)?;
        let shared = Arc::new(Shared {
            gw: gateway,
            stats: ControlStats::default(),
            limits,
            closing: AtomicBool::new(false),
            gate: RwLock::new(()),
            clients: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(1),
            records: std::sync::atomic::AtomicUsize::new(0),
            serving: AtomicBool::new(false),
            server_writers: Mutex::new((0, HashMap::new())),
        });
        // Weak: the servers live in the gateway, which the shared state holds.
        let weak: std::sync::Weak<dyn driver_api::Control> = Arc::downgrade(&shared) as _;
        shared.gw.control_link().join(weak);
        let listener = bound
            .listener
            .try_clone()
            .map_err(|source| SocketError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        if let Some(node) = shared.gw.zenoh() {
            // Weak: the node lives in the gateway, which the shared state holds.
            let weak = Arc::downgrade(&shared);
            crate::forward::serve_control(node, move |request| match weak.upgrade() {
                Some(shared) => remote_request(&shared, request),
                None => {
                    json!({"error": {"kind": "stopping", "message": "the control server is closed"}})
                }
            });
        }
        Ok(ControlServer {
            bound,
            shared,
            listener: Some(listener),
            accept: None,
        })
    }

    /// Starts answering, from a thread of its own (once; later calls do nothing).
    pub fn open(&mut self) -> Result<(), SocketError> {
        let Some(listener) = self.listener.take() else {
            return Ok(());
        };
        self.shared.serving.store(true, Ordering::Release);
        let s = self.shared.clone();
        let accept = std::thread::Builder::new()
            .name("hwgw-control".into())
            .spawn(move || accept_loop(&s, &listener))
            .map_err(|source| SocketError::Io {
                path: self.bound.path.clone(),
                source,
            })?;
        self.accept = Some(accept);
        Ok(())
    }

    /// The socket path.
    pub fn path(&self) -> &Path {
        &self.bound.path
    }

    /// Counters.
    pub fn stats(&self) -> &ControlStats {
        &self.shared.stats
    }

    /// Stops serving: no new request is carried out, the ones under way get up to
    /// [`CLOSE_WAIT`] to finish (a call can wait for a component's next period; the stop
    /// does not), every client is disconnected, the socket is removed. Idempotent.
    pub fn close(&mut self) {
        self.shared.closing.store(true, Ordering::Release);
        let deadline = std::time::Instant::now() + CLOSE_WAIT;
        loop {
            match self.shared.gate.try_write() {
                Ok(_) | Err(std::sync::TryLockError::Poisoned(_)) => break,
                Err(std::sync::TryLockError::WouldBlock) => {}
            }
            if std::time::Instant::now() >= deadline {
                tracing::warn!(
                    "control socket: requests still under way after {CLOSE_WAIT:?}; \
                     disconnecting their clients and stopping without them"
                );
                break;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        for (_, c) in rtt::lock(&self.shared.clients).drain() {
            let _ = c.shutdown(std::net::Shutdown::Both);
        }
        if let Some(t) = self.accept.take() {
            let _ = t.join();
        }
        self.bound.remove();
    }
}

impl Drop for ControlServer {
    fn drop(&mut self) {
        self.close();
    }
}

/// Accepts clients until closing; out of file descriptors it backs off (up to a second)
/// and tries again, logging once per episode.
fn accept_loop(shared: &Arc<Shared>, listener: &std::os::unix::net::UnixListener) {
    use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
    let mut backoff = Duration::from_millis(10);
    let mut starved = false;
    while !shared.closing.load(Ordering::Acquire) {
        let mut fds = [PollFd::new(listener.as_fd(), PollFlags::POLLIN)];
        match poll(&mut fds, PollTimeout::from(100u16)) {
            Ok(0) | Err(nix::Error::EINTR) => continue,
            Ok(_) => {}
            Err(e) => {
                tracing::error!("control socket: poll: {e}");
                std::thread::sleep(backoff);
                continue;
            }
        }
        let refused = match listener.accept() {
            Ok((conn, _)) => admit(shared, conn).err(),
            Err(e)
                if e.kind() == std::io::ErrorKind::Interrupted
                    || e.kind() == std::io::ErrorKind::WouldBlock =>
            {
                continue;
            }
            Err(e) => Some(e),
        };
        match refused {
            None => {
                if starved {
                    tracing::info!("control socket: accepting clients again");
                    starved = false;
                }
                backoff = Duration::from_millis(10);
            }
            Some(e) if out_of_resources(&e) => {
                shared.stats.accept_failures.fetch_add(1, Ordering::Relaxed);
                if !starved {
                    tracing::error!(
                        "control socket: cannot take a client: {e}; backing off until clients leave"
                    );
                    starved = true;
                }
                std::thread::sleep(backoff);
                backoff = (backoff * 2).min(Duration::from_secs(1));
            }
            Some(e) => tracing::warn!("control socket: accept: {e}"),
        }
    }
}

/// True for the errors that pass when clients leave (descriptors, memory, threads).
fn out_of_resources(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM | libc::EAGAIN)
    )
}

/// Serves a new client on a thread of its own, or turns it away beyond the limit. An
/// error when the client could not be taken for want of resources (a descriptor for its
/// second handle, a thread): it is told so, and the caller backs off.
fn admit(shared: &Arc<Shared>, conn: UnixStream) -> std::io::Result<()> {
    let turn_away = |conn: UnixStream, kind: ErrorKind, why: String| {
        let _ = conn.set_write_timeout(Some(Duration::from_millis(100)));
        let _ = send(&conn, &Reply::error(Value::Null, kind, why));
    };
    let id = shared.next_id.fetch_add(1, Ordering::Relaxed);
    {
        let mut clients = rtt::lock(&shared.clients);
        if shared.closing.load(Ordering::Acquire) {
            return Ok(());
        }
        if clients.len() >= shared.limits.clients {
            shared.stats.refused.fetch_add(1, Ordering::Relaxed);
            let why = format!(
                "{} clients are connected, the most this gateway takes; try again later",
                shared.limits.clients
            );
            turn_away(conn, ErrorKind::Busy, why);
            return Ok(());
        }
        match conn.try_clone() {
            Ok(clone) => clients.insert(id, clone),
            Err(e) => {
                turn_away(
                    conn,
                    ErrorKind::Busy,
                    format!("the gateway cannot take a client now ({e}); try again later"),
                );
                return Err(e);
            }
        };
    }
    let s = shared.clone();
    let spawned = std::thread::Builder::new()
        .name("hwgw-client".into())
        .spawn(move || {
            // Leaves the table however serving ends (a panic in a request included).
            let _leave = Leave(&s, id);
            serve_client(&s, conn);
        });
    if let Err(e) = spawned {
        // The client's handle went with the closure; its clone in `clients` goes now.
        rtt::lock(&shared.clients).remove(&id);
        return Err(e);
    }
    shared.stats.clients.fetch_add(1, Ordering::Relaxed);
    Ok(())
}

/// A request under way, counted while it lives.
struct UnderWay<'a>(&'a AtomicU64);

impl<'a> UnderWay<'a> {
    fn new(gauge: &'a AtomicU64) -> Self {
        gauge.fetch_add(1, Ordering::Relaxed);
        UnderWay(gauge)
    }
}

impl Drop for UnderWay<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A served client's entry in the table of clients, removed when its thread ends.
struct Leave<'a>(&'a Shared, u64);

impl Drop for Leave<'_> {
    fn drop(&mut self) {
        rtt::lock(&self.0.clients).remove(&self.1);
    }
}

/// Reads one line of at most `MAX_LINE` bytes. `Ok(None)` at end of stream;
/// `Err(TooLong)` after skipping the rest of an oversized line.
fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>) -> std::io::Result<Option<Result<(), ()>>> {
    buf.clear();
    let mut too_long = false;
    loop {
        let chunk = r.fill_buf()?;
        if chunk.is_empty() {
            return Ok(if buf.is_empty() && !too_long {
                None
            } else {
                Some(if too_long { Err(()) } else { Ok(()) })
            });
        }
        let (take, done) = match chunk.iter().position(|b| *b == b'\n') {
            Some(i) => (i + 1, true),
            None => (chunk.len(), false),
        };
        if !too_long {
            if buf.len() + take > MAX_LINE + 1 {
                too_long = true;
                buf.clear();
            } else {
                buf.extend_from_slice(&chunk[..take]);
            }
        }
        r.consume(take);
        if done {
            return Ok(Some(if too_long { Err(()) } else { Ok(()) }));
        }
    }
}

fn serve_client(shared: &Shared, conn: UnixStream) {
    // One handle reads and writes (no second descriptor to run out of).
    let _ = conn.set_read_timeout(Some(shared.limits.idle));
    let _ = conn.set_write_timeout(Some(shared.limits.idle));
    let out = &conn;
    let mut reader = BufReader::new(&conn);
    let mut writers: Writers = HashMap::new();
    let mut generation = shared.gw.generation.load(Ordering::Acquire);
    let mut buf = Vec::new();
    let stats = &shared.stats;
    loop {
        let reply = match read_line(&mut reader, &mut buf) {
            Ok(None) => return,
            Err(e) => {
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) {
                    stats.idle_closed.fetch_add(1, Ordering::Relaxed);
                }
                return;
            }
            Ok(Some(Err(()))) => Reply::error(
                Value::Null,
                ErrorKind::TooLong,
                format!("request longer than {MAX_LINE} bytes"),
            ),
            Ok(Some(Ok(()))) => {
                let text = String::from_utf8_lossy(&buf);
                if text.trim().is_empty() {
                    continue;
                }
                match parse(&text) {
                    Err(reply) => reply,
                    Ok((
                        id,
                        Request::Watch {
                            component,
                            port,
                            count,
                        },
                    )) => match watch(shared, &component, &port, count, &id, out) {
                        // The stream ended because the client went away or had enough.
                        Ok(()) => return,
                        Err(Fail(kind, message)) => Reply::error(id, kind, message),
                    },
                    Ok((
                        id,
                        Request::Record {
                            ports,
                            devices,
                            steps,
                            buffer,
                        },
                    )) => {
                        let ask = crate::recorder::stream::Ask {
                            ports: &ports,
                            devices,
                            steps,
                            buffer,
                        };
                        match record(shared, &ask, &id, out) {
                            Ok(()) => return,
                            Err(Fail(kind, message)) => Reply::error(id, kind, message),
                        }
                    }
                    Ok((id, req)) => {
                        drop_stale(&shared.gw, &mut generation, &mut writers);
                        carry_out(shared, id, &req, &mut writers, true)
                    }
                }
            }
        };
        stats.requests.fetch_add(1, Ordering::Relaxed);
        if matches!(reply.body, Body::Error(_)) {
            stats.errors.fetch_add(1, Ordering::Relaxed);
        }
        if send(out, &reply).is_err() {
            return;
        }
    }
}

/// One request, carried out under the gate: never once the server is closing.
fn carry_out(
    shared: &Shared,
    id: Value,
    req: &Request,
    writers: &mut Writers,
    forward: bool,
) -> Reply {
    let stopping = || {
        Reply::error(
            id.clone(),
            ErrorKind::Stopping,
            "the gateway is stopping: its outputs are going to their safe values",
        )
    };
    if shared.closing.load(Ordering::Acquire) {
        return stopping();
    }
    let _open = shared.gate.read().unwrap_or_else(|p| p.into_inner());
    if shared.closing.load(Ordering::Acquire) {
        return stopping();
    }
    let _counted = UnderWay::new(&shared.stats.under_way);
    let gw = &shared.gw;
    let local = |c: &str| gw.runtime().component(c).is_ok();
    let here = |r: &Request| handle(gw, shared.report(), r, &mut HashMap::new());
    let answer = forward
        .then(|| crate::forward::forward(gw.zenoh(), &local, req, &here))
        .flatten()
        .unwrap_or_else(|| handle(gw, shared.report(), req, writers));
    match answer {
        Ok(v) => Reply {
            id,
            body: Body::Ok(v),
        },
        Err(Fail(kind, message)) => Reply::error(id, kind, message),
    }
}

/// The gateway's servers ask as a client of the socket would, once it serves (before, the
/// gateway has not started: `unavailable`); streams are not served this way.
impl driver_api::Control for Shared {
    fn request(&self, request: Value) -> Result<Value, driver_api::ControlError> {
        self.admit()?;
        let reply = match parse(&request.to_string()) {
            Err(reply) => reply,
            Ok((id, Request::Watch { .. } | Request::Record { .. })) => Reply::error(
                id,
                ErrorKind::BadRequest,
                "streams (watch, record) are served on the control socket only",
            ),
            Ok((id, req @ Request::Set { .. })) => {
                let mut kept = rtt::lock(&self.server_writers);
                let (generation, writers) = &mut *kept;
                drop_stale(&self.gw, generation, writers);
                carry_out(self, id, &req, writers, true)
            }
            Ok((id, req)) => carry_out(self, id, &req, &mut HashMap::new(), true),
        };
        match reply.body {
            Body::Ok(v) => Ok(v),
            Body::Error(e) => {
                self.stats.errors.fetch_add(1, Ordering::Relaxed);
                Err(control_error(e.kind, e.message))
            }
            Body::Event(_) | Body::Records(_) | Body::Heartbeat(_) => Err(
                driver_api::ControlError::new("failed", "a stream's line where a reply was due"),
            ),
        }
    }

    fn stream(
        &self,
        request: Value,
        each: &mut dyn FnMut(Value) -> bool,
    ) -> Result<(), driver_api::ControlError> {
        self.stream_to(request, each)
    }
}

/// A control error of `kind` for the gateway's servers.
fn control_error(kind: ErrorKind, message: impl Into<String>) -> driver_api::ControlError {
    let kind = serde_json::to_value(kind).unwrap_or(Value::Null);
    driver_api::ControlError::new(kind.as_str().unwrap_or("failed"), message)
}

impl Shared {
    /// A server's request is carried out once the control server serves (before, the
    /// gateway has not started: `unavailable`), and counted.
    fn admit(&self) -> Result<(), driver_api::ControlError> {
        if !self.serving.load(Ordering::Acquire) {
            return Err(driver_api::ControlError::new(
                "unavailable",
                "the gateway is starting",
            ));
        }
        if self.closing.load(Ordering::Acquire) {
            return Err(control_error(
                ErrorKind::Stopping,
                "the gateway is stopping: its outputs are going to their safe values",
            ));
        }
        self.stats.requests.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// The in-process stream of [`driver_api::Control::stream`].
    fn stream_to(
        &self,
        request: Value,
        each: &mut dyn FnMut(Value) -> bool,
    ) -> Result<(), driver_api::ControlError> {
        self.admit()?;
        let (id, ports, devices, steps, buffer) = match parse(&request.to_string()) {
            Ok((
                id,
                Request::Record {
                    ports,
                    devices,
                    steps,
                    buffer,
                },
            )) => (id, ports, devices, steps, buffer),
            Ok((_, r)) => {
                let m = format!("{} is not a stream: ask it with request", r.cmd());
                return Err(control_error(ErrorKind::BadRequest, m));
            }
            Err(reply) => match reply.body {
                Body::Error(e) => return Err(control_error(e.kind, e.message)),
                _ => return Err(control_error(ErrorKind::BadRequest, "not a request")),
            },
        };
        let ask = crate::recorder::stream::Ask {
            ports: &ports,
            devices,
            steps,
            buffer,
        };
        let mut sink = |reply: &Reply| match &reply.body {
            Body::Ok(v) => each(v.clone()),
            Body::Records(b) => match serde_json::to_value(b) {
                Ok(v) => each(json!({ "records": v })),
                Err(_) => false,
            },
            _ => true,
        };
        record_to(self, &ask, &id, &mut sink).map_err(|Fail(kind, m)| control_error(kind, m))
    }
}

/// A control request of another gateway (through Zenoh), carried out here as one from
/// the socket; its reply body without `id`.
fn remote_request(shared: &Shared, request: Value) -> Value {
    shared.stats.requests.fetch_add(1, Ordering::Relaxed);
    let reply = match parse(&request.to_string()) {
        Err(reply) => reply,
        Ok((id, Request::Watch { .. } | Request::Record { .. })) => Reply::error(
            id,
            ErrorKind::BadRequest,
            "streams (watch, record) are not served to other gateways",
        ),
        // Reloading and changing the deployment are this host's operator's to ask
        // (`hwgw reload`, SIGHUP, `hwgw load`, …).
        Ok((id, r)) if r.is_local_only() => Reply::error(
            id,
            ErrorKind::BadRequest,
            format!(
                "{} is not served to other gateways: ask on the gateway's own host",
                r.cmd()
            ),
        ),
        // Carried out here, never forwarded again (no request goes round the gateways).
        Ok((id, req)) => carry_out(shared, id, &req, &mut HashMap::new(), false),
    };
    if matches!(reply.body, Body::Error(_)) {
        shared.stats.errors.fetch_add(1, Ordering::Relaxed);
    }
    let mut v = serde_json::to_value(&reply).unwrap_or(Value::Null);
    if let Some(o) = v.as_object_mut() {
        o.remove("id");
    }
    v
}

fn send(mut out: &UnixStream, reply: &Reply) -> std::io::Result<()> {
    let mut line = serde_json::to_string(reply).map_err(std::io::Error::other)?;
    line.push('\n');
    out.write_all(line.as_bytes())
}

/// A request line as its `id` and [`Request`], or the error reply.
fn parse(text: &str) -> Result<(Value, Request), Reply> {
    let mut v: Value = serde_json::from_str(text)
        .map_err(|e| Reply::error(Value::Null, ErrorKind::Parse, format!("not JSON: {e}")))?;
    let Some(obj) = v.as_object_mut() else {
        return Err(Reply::error(
            Value::Null,
            ErrorKind::BadRequest,
            "a request is a JSON object",
        ));
    };
    let id = obj.remove("id").unwrap_or(Value::Null);
    let cmd = match obj.get("cmd") {
        Some(Value::String(c)) => c.clone(),
        _ => {
            return Err(Reply::error(
                id,
                ErrorKind::BadRequest,
                "missing string field \"cmd\"",
            ));
        }
    };
    if !crate::protocol::COMMANDS.iter().any(|c| c.cmd == cmd) {
        let message = format!("unknown command {cmd:?}; commands: {}", Request::names());
        return Err(Reply::error(id, ErrorKind::UnknownCommand, message));
    }
    match serde_json::from_value(v) {
        Ok(req) => Ok((id, req)),
        Err(e) => Err(Reply::error(
            id,
            ErrorKind::BadRequest,
            format!("{cmd}: {e}"),
        )),
    }
}

/// Streams new values of an output port to `out` until the client closes or `count`
/// values were sent. Samples travel through a 256-deep buffer connection, so bursts
/// between two polls are not lost (overflow is counted on the connection).
fn watch(
    shared: &Shared,
    component: &str,
    port: &str,
    count: Option<u64>,
    id: &Value,
    out: &UnixStream,
) -> Result<(), Fail> {
    let t = shared
        .gw
        .runtime()
        .component(component)
        .map_err(not_found)?;
    let port = t.port(port).map_err(not_found)?;
    let mut reader = port.reader(ConnPolicy::buffer(256)).map_err(failed)?;
    let count = count.unwrap_or(u64::MAX);
    let mut sent = 0;
    // Tell the client the watch is in place before any value.
    let ack = Reply {
        id: id.clone(),
        body: Body::Ok(json!("watching")),
    };
    send(out, &ack).map_err(failed)?;
    let mut last_line = std::time::Instant::now();
    while sent < count && !shared.closing.load(Ordering::Acquire) {
        if last_line.elapsed() >= crate::protocol::HEARTBEAT {
            let beat = Reply {
                id: id.clone(),
                body: Body::Heartbeat(rtt::time::Clock::now(&rtt::time::MonotonicClock).as_nanos()),
            };
            if send(out, &beat).is_err() {
                return Ok(());
            }
            last_line = std::time::Instant::now();
        }
        match reader.read() {
            (rtt::port::FlowStatus::NewData, Some(value)) => {
                let event = Reply {
                    id: id.clone(),
                    body: Body::Event(Event {
                        status: rtt::port::FlowStatus::NewData,
                        value,
                    }),
                };
                if send(out, &event).is_err() {
                    return Ok(());
                }
                last_line = std::time::Instant::now();
                sent += 1;
            }
            _ => {
                // Nothing new: poll again shortly; notice a client that has gone away.
                std::thread::sleep(std::time::Duration::from_millis(5));
                if peer_closed(out) {
                    return Ok(());
                }
            }
        }
    }
    Ok(())
}

/// A `record` stream: what it records, then batches until the client goes away or the
/// server closes.
fn record(
    shared: &Shared,
    ask: &crate::recorder::stream::Ask<'_>,
    id: &Value,
    out: &UnixStream,
) -> Result<(), Fail> {
    // A client that stops reading ends its stream (its slot freed) within this long.
    out.set_write_timeout(Some(RECORD_WRITE_TIMEOUT))
        .map_err(failed)?;
    let mut sink = |reply: &Reply| send(out, reply).is_ok() && !peer_closed(out);
    record_to(shared, ask, id, &mut sink)
}

/// A `record` stream: its acknowledgement, then its batches, each to `sink` (as reply
/// lines with `id`) until it returns false or the server closes.
fn record_to(
    shared: &Shared,
    ask: &crate::recorder::stream::Ask<'_>,
    id: &Value,
    sink: &mut dyn FnMut(&Reply) -> bool,
) -> Result<(), Fail> {
    use crate::recorder::stream;
    let taken = shared.records.fetch_add(1, Ordering::AcqRel);
    // Given back however this returns.
    let _slot = ReleaseOnDrop(&shared.records);
    if taken >= MAX_RECORD_STREAMS {
        return Err(Fail(
            ErrorKind::Busy,
            format!("{MAX_RECORD_STREAMS} record streams are under way already; stop one first"),
        ));
    }
    let (taps, start) = stream::open(&shared.gw, ask).map_err(|(kind, m)| Fail(kind, m))?;
    let ack = Reply {
        id: id.clone(),
        body: Body::Ok(serde_json::to_value(start).map_err(failed)?),
    };
    if !sink(&ack) {
        return Ok(());
    }
    let batch = |b| {
        let reply = Reply {
            id: id.clone(),
            body: Body::Records(b),
        };
        sink(&reply)
    };
    stream::pump(taps, batch, || shared.closing.load(Ordering::Acquire));
    Ok(())
}

/// Takes one from a counter when dropped.
struct ReleaseOnDrop<'a>(&'a std::sync::atomic::AtomicUsize);

impl Drop for ReleaseOnDrop<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// True when the client closed its end (a peek finds end of stream or an error).
fn peer_closed(s: &UnixStream) -> bool {
    use nix::sys::socket::{MsgFlags, recv};
    use std::os::fd::AsRawFd;
    let mut b = [0u8; 1];
    match recv(
        s.as_raw_fd(),
        &mut b,
        MsgFlags::MSG_PEEK | MsgFlags::MSG_DONTWAIT,
    ) {
        Ok(0) => true,
        Ok(_) | Err(nix::Error::EAGAIN) => false,
        Err(_) => true,
    }
}

#[cfg(test)]
mod tests {
    use crate::protocol::Request;

    #[test]
    fn the_documented_table_is_the_table() {
        let doc = include_str!("control.rs");
        for line in Request::table().lines() {
            assert!(
                doc.contains(&format!("//! {line}")),
                "control.rs's documentation lacks the line:\n//! {line}\n(it must show Request::table())"
            );
        }
    }
}
