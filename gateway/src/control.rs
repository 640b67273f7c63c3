//! The control socket: line-delimited JSON over a Unix domain socket, typed by
//! [`crate::protocol`].
//!
//! Each request is one JSON object on one line with an `id` (echoed back) and a `cmd`;
//! each reply is one line: `{"id": …, "ok": …}` or `{"id": …, "error": {"kind": …,
//! "message": …}}`. A malformed, unknown or oversized request gets an error reply and the
//! connection stays open; every client has its own thread, so a slow one delays nobody.
//!
//! | cmd | fields | ok |
//! |---|---|---|
//! | `ls` | — | `[{"name", "state"}]` of every component |
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
//! | `watch` | `component`, `port`, optional `count` | `"watching"`, then a stream: one `{"id", "event": {"status", "value"}}` line per new value (all of them, `count` at most), until the client closes |
//!
//! Error kinds: `parse`, `too_long`, `bad_request`, `unknown_command`, `not_found`,
//! `failed`.
//!
//! ```text
//! $ echo '{"id":1,"cmd":"get","component":"sim0.ai","port":"ch3"}' | socat - UNIX:/run/hwgw/hwgw.sock
//! {"id":1,"ok":2.4998}
//! ```

use crate::deploy::Gateway;
use crate::protocol::{
    Body, ComponentEntry, ComponentStatus, Description, DeviceStatus, ErrorKind, Event, Reply,
    Request, StatusReport, Target,
};
use rtt::component::DynWriter;
use rtt::port::ConnPolicy;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Longest request line accepted, bytes.
pub const MAX_LINE: usize = 64 * 1024;

/// The default socket path: /run/hwgw/hwgw.sock for root (the service), else
/// `$XDG_RUNTIME_DIR/hwgw.sock`, else /tmp/hwgw-UID.sock.
pub fn default_socket() -> PathBuf {
    let uid = nix::unistd::getuid();
    if uid.is_root() {
        return PathBuf::from("/run/hwgw/hwgw.sock");
    }
    match std::env::var_os("XDG_RUNTIME_DIR") {
        Some(dir) => Path::new(&dir).join("hwgw.sock"),
        None => PathBuf::from(format!("/tmp/hwgw-{uid}.sock")),
    }
}

/// Counters of the control server.
#[derive(Debug, Default)]
pub struct ControlStats {
    /// Clients accepted.
    pub clients: AtomicU64,
    /// Requests answered.
    pub requests: AtomicU64,
    /// Requests answered with an error.
    pub errors: AtomicU64,
}

/// The running control server; dropping it stops accepting and removes the socket.
pub struct ControlServer {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    stats: Arc<ControlStats>,
}

impl ControlServer {
    /// Binds `path` (mode 0660; its directory is created; a stale socket is replaced) and
    /// serves `gateway` on it from a thread of its own.
    pub fn start(gateway: Arc<Gateway>, path: &Path) -> std::io::Result<ControlServer> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        if path.exists() {
            if UnixStream::connect(path).is_ok() {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::AddrInUse,
                    format!("{}: another hwgw is serving this socket", path.display()),
                ));
            }
            std::fs::remove_file(path)?;
        }
        let listener = UnixListener::bind(path)?;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o660))?;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(ControlStats::default());
        let (s, st) = (stop.clone(), stats.clone());
        std::thread::Builder::new()
            .name("hwgw-control".into())
            .spawn(move || {
                for conn in listener.incoming() {
                    if s.load(Ordering::Acquire) {
                        break;
                    }
                    let Ok(conn) = conn else { continue };
                    st.clients.fetch_add(1, Ordering::Relaxed);
                    let (gw, st2) = (gateway.clone(), st.clone());
                    let _ = std::thread::Builder::new()
                        .name("hwgw-client".into())
                        .spawn(move || serve_client(&gw, conn, &st2));
                }
            })?;
        Ok(ControlServer {
            path: path.to_path_buf(),
            stop,
            stats,
        })
    }

    /// The socket path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Counters.
    pub fn stats(&self) -> &ControlStats {
        &self.stats
    }
}

impl Drop for ControlServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        // Wake the accept loop so it sees the flag.
        let _ = UnixStream::connect(&self.path);
        let _ = std::fs::remove_file(&self.path);
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

fn serve_client(gw: &Gateway, conn: UnixStream, stats: &ControlStats) {
    let Ok(mut out) = conn.try_clone() else {
        return;
    };
    let mut reader = BufReader::new(conn.take(u64::MAX));
    let mut writers: HashMap<(String, String), Box<dyn DynWriter>> = HashMap::new();
    let mut buf = Vec::new();
    loop {
        let reply = match read_line(&mut reader, &mut buf) {
            Ok(None) | Err(_) => return,
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
                    )) => match watch(gw, &component, &port, count, &id, &mut out) {
                        // The stream ended because the client went away or had enough.
                        Ok(()) => return,
                        Err(Fail(kind, message)) => Reply::error(id, kind, message),
                    },
                    Ok((id, req)) => match handle(gw, &req, &mut writers) {
                        Ok(v) => Reply {
                            id,
                            body: Body::Ok(v),
                        },
                        Err(Fail(kind, message)) => Reply::error(id, kind, message),
                    },
                }
            }
        };
        stats.requests.fetch_add(1, Ordering::Relaxed);
        if matches!(reply.body, Body::Error(_)) {
            stats.errors.fetch_add(1, Ordering::Relaxed);
        }
        if send(&mut out, &reply).is_err() {
            return;
        }
    }
}

fn send(out: &mut UnixStream, reply: &Reply) -> std::io::Result<()> {
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
    gw: &Gateway,
    component: &str,
    port: &str,
    count: Option<u64>,
    id: &Value,
    out: &mut UnixStream,
) -> Result<(), Fail> {
    let t = gw.runtime().component(component).map_err(not_found)?;
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
    while sent < count {
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

/// Every device's health, every card's bus counters, and every component's state and
/// activity figures.
fn status(gw: &Gateway) -> StatusReport {
    let reg = gw.runtime().registry();
    let devices = reg
        .entries()
        .into_iter()
        .filter(|e| e.info.alias_of.is_none())
        .filter_map(|e| {
            let h = reg.health(e.interface, &e.info.name)?;
            Some(DeviceStatus {
                interface: e.interface,
                status: h.status,
                age_s: h.age().map(|a| a.as_secs_f64()),
                last_error: h.last_error.map(|e| e.to_string()),
                name: e.info.name,
            })
        })
        .collect();
    let components = gw
        .runtime()
        .components()
        .iter()
        .map(|t| {
            let s = t.stats();
            ComponentStatus {
                name: t.name().to_string(),
                state: t.state(),
                steps: s.steps,
                overruns: s.overruns,
                healthy: s.healthy,
                realtime: s.realtime,
                lateness_p99_us: s.lateness_quantile(0.99).as_secs_f64() * 1e6,
                step_mean_us: s.step_mean().as_secs_f64() * 1e6,
                counters: t.counters(),
            }
        })
        .collect();
    StatusReport {
        health: gw.health().err().unwrap_or_else(|| "ok".into()),
        devices,
        cards: gw.card_status(),
        components,
    }
}

/// Why a request failed: its kind and message.
struct Fail(ErrorKind, String);

fn not_found(e: impl std::fmt::Display) -> Fail {
    Fail(ErrorKind::NotFound, e.to_string())
}

fn failed(e: impl std::fmt::Display) -> Fail {
    Fail(ErrorKind::Failed, e.to_string())
}

fn to_value(v: impl serde::Serialize) -> Result<Value, Fail> {
    serde_json::to_value(v).map_err(failed)
}

fn handle(
    gw: &Gateway,
    req: &Request,
    writers: &mut HashMap<(String, String), Box<dyn DynWriter>>,
) -> Result<Value, Fail> {
    let rt = gw.runtime();
    let component = |name: &str| rt.component(name).map_err(not_found);
    match req {
        Request::Ls => to_value(
            rt.components()
                .iter()
                .map(|t| ComponentEntry {
                    name: t.name().to_string(),
                    state: t.state(),
                })
                .collect::<Vec<_>>(),
        ),
        Request::Devices => to_value(rt.registry().entries()),
        Request::Status => to_value(status(gw)),
        Request::Describe { component: c } => {
            let t = component(c)?;
            to_value(Description {
                name: t.name().to_string(),
                state: t.state(),
                ports: t.ports(),
                operations: t.operations(),
                properties: t.properties().list(),
                attributes: t.attributes().list(),
                counters: t.counters(),
                activity: t.stats(),
            })
        }
        Request::Get {
            component: c,
            target: Target::Port(port),
        } => {
            let p = component(c)?.port(port).map_err(not_found)?;
            p.last_value()
                .map_err(failed)
                .map(|v| v.unwrap_or(Value::Null))
        }
        Request::Get {
            component: c,
            target: Target::Property(prop),
        } => component(c)?
            .properties()
            .get_value(prop)
            .map_err(not_found),
        Request::Set {
            component: c,
            target: Target::Port(port),
            value,
        } => {
            let t = component(c)?;
            let key = (t.name().to_string(), port.clone());
            if !writers.contains_key(&key) {
                let p = t.port(port).map_err(not_found)?;
                writers.insert(
                    key.clone(),
                    p.writer(ConnPolicy::buffer(16)).map_err(failed)?,
                );
            }
            match writers.get_mut(&key) {
                Some(w) => w.write(value.clone()).map_err(failed).map(|()| Value::Null),
                None => Err(failed("writer vanished")),
            }
        }
        Request::Set {
            component: c,
            target: Target::Property(prop),
            value,
        } => component(c)?
            .properties()
            .set_value(prop, value.clone())
            .map_err(failed)
            .map(|()| Value::Null),
        Request::Call {
            component: c,
            operation,
            args,
        } => component(c)?
            .call_value(operation, args.clone())
            .map_err(|e| match e {
                rtt::component::CallOrIntrospect::Introspect(e) => not_found(e),
                rtt::component::CallOrIntrospect::Call(e) => failed(e),
            }),
        Request::Configure { component: c } => lifecycle(component(c)?, |t| t.configure()),
        Request::Start { component: c } => lifecycle(component(c)?, |t| t.start()),
        Request::Stop { component: c } => lifecycle(component(c)?, |t| t.stop()),
        Request::Cleanup { component: c } => lifecycle(component(c)?, |t| t.cleanup()),
        Request::Recover { component: c } => lifecycle(component(c)?, |t| t.recover()),
        Request::Watch { .. } => Err(Fail(
            ErrorKind::BadRequest,
            "watch streams: it is served on its own".into(),
        )),
    }
}

/// Runs a lifecycle command; the answer is the new state.
fn lifecycle(
    t: rtt::TaskContext,
    f: impl FnOnce(&rtt::TaskContext) -> Result<(), rtt::component::LifecycleError>,
) -> Result<Value, Fail> {
    f(&t).map_err(failed)?;
    to_value(t.state())
}
