//! The control socket: line-delimited JSON over a Unix domain socket.
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
//! | `get` | `component` and `port` or `property` | the output port's last value, or the property's value |
//! | `set` | `component`, `port` or `property`, `value` | `null`; a port must be an input port |
//! | `call` | `component`, `operation`, `args` (array) | the result |
//! | `configure`, `start`, `stop`, `cleanup`, `recover` | `component` | the new state |
//! | `status` | — | every device's health and every component's state and timing |
//! | `watch` | `component`, `port`, optional `count` | a stream: one `{"id", "event": {"status", "value"}}` line per new value (all of them, `count` at most), until the client closes |
//!
//! Error kinds: `parse`, `too_long`, `bad_request`, `unknown_command`, `not_found`,
//! `failed`.
//!
//! ```text
//! $ echo '{"id":1,"cmd":"get","component":"sim0.ai","port":"ch3"}' | socat - UNIX:/run/hwgw/hwgw.sock
//! {"id":1,"ok":2.4998}
//! ```

use crate::deploy::Gateway;
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

/// Error reply kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Parse,
    TooLong,
    BadRequest,
    UnknownCommand,
    NotFound,
    Failed,
}

impl Kind {
    fn as_str(self) -> &'static str {
        match self {
            Kind::Parse => "parse",
            Kind::TooLong => "too_long",
            Kind::BadRequest => "bad_request",
            Kind::UnknownCommand => "unknown_command",
            Kind::NotFound => "not_found",
            Kind::Failed => "failed",
        }
    }
}

struct Fail(Kind, String);

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
            Ok(Some(Err(()))) => error_reply(
                Value::Null,
                Kind::TooLong,
                format!("request longer than {MAX_LINE} bytes"),
            ),
            Ok(Some(Ok(()))) => {
                let text = String::from_utf8_lossy(&buf);
                if text.trim().is_empty() {
                    continue;
                }
                match serde_json::from_str::<Value>(&text) {
                    Err(e) => error_reply(Value::Null, Kind::Parse, format!("not JSON: {e}")),
                    Ok(req) if req.get("cmd").and_then(Value::as_str) == Some("watch") => {
                        let id = req.get("id").cloned().unwrap_or(Value::Null);
                        match watch(gw, &req, &id, &mut out) {
                            // The stream ended because the client went away or had enough.
                            Ok(()) => return,
                            Err(Fail(kind, message)) => error_reply(id, kind, message),
                        }
                    }
                    Ok(req) => {
                        let id = req.get("id").cloned().unwrap_or(Value::Null);
                        match handle(gw, &req, &mut writers) {
                            Ok(v) => json!({"id": id, "ok": v}),
                            Err(Fail(kind, message)) => error_reply(id, kind, message),
                        }
                    }
                }
            }
        };
        stats.requests.fetch_add(1, Ordering::Relaxed);
        if reply.get("error").is_some() {
            stats.errors.fetch_add(1, Ordering::Relaxed);
        }
        let mut line = reply.to_string();
        line.push('\n');
        if out.write_all(line.as_bytes()).is_err() {
            return;
        }
    }
}

/// Streams new values of an output port to `out` until the client closes or `count`
/// values were sent. Samples travel through a 256-deep buffer connection, so bursts
/// between two polls are not lost (overflow is counted on the connection).
fn watch(gw: &Gateway, req: &Value, id: &Value, out: &mut UnixStream) -> Result<(), Fail> {
    let t = gw
        .runtime()
        .component(field(req, "component")?)
        .map_err(not_found)?;
    let port = t.port(field(req, "port")?).map_err(not_found)?;
    let mut reader = port.reader(ConnPolicy::buffer(256)).map_err(failed)?;
    let count = req.get("count").and_then(Value::as_u64).unwrap_or(u64::MAX);
    let mut sent = 0;
    // Tell the client the watch is in place before any value.
    let mut line = json!({"id": id, "ok": "watching"}).to_string();
    line.push('\n');
    out.write_all(line.as_bytes()).map_err(failed)?;
    while sent < count {
        match reader.read() {
            (rtt::port::FlowStatus::NewData, Some(value)) => {
                let mut line =
                    json!({"id": id, "event": {"status": "new_data", "value": value}}).to_string();
                line.push('\n');
                if out.write_all(line.as_bytes()).is_err() {
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

/// Every device's health and every component's state and activity figures.
fn status(gw: &Gateway) -> Value {
    let reg = gw.runtime().registry();
    let mut devices = Vec::new();
    for e in reg.entries() {
        if e.info.alias_of.is_some() {
            continue;
        }
        let n = &e.info.name;
        if let Some(h) = reg.health(e.interface, n) {
            devices.push(json!({
                "interface": e.interface,
                "name": n,
                "status": h.status,
                "age_s": h.age().map(|a| a.as_secs_f64()),
                "last_error": h.last_error.map(|e| e.to_string()),
            }));
        }
    }
    let components: Vec<Value> = gw
        .runtime()
        .components()
        .iter()
        .map(|t| {
            let s = t.stats();
            json!({
                "name": t.name(),
                "state": t.state(),
                "steps": s.steps,
                "overruns": s.overruns,
                "healthy": s.healthy,
                "realtime": s.realtime,
                "lateness_p99_us": s.lateness_quantile(0.99).as_secs_f64() * 1e6,
                "step_mean_us": s.step_mean().as_secs_f64() * 1e6,
                "counters": t.counters(),
            })
        })
        .collect();
    json!({
        "health": gw.health().err().unwrap_or_else(|| "ok".into()),
        "devices": devices,
        "cards": gw.card_status(),
        "components": components,
    })
}

fn error_reply(id: Value, kind: Kind, message: String) -> Value {
    json!({"id": id, "error": {"kind": kind.as_str(), "message": message}})
}

fn field<'a>(req: &'a Value, name: &str) -> Result<&'a str, Fail> {
    req.get(name)
        .and_then(Value::as_str)
        .ok_or_else(|| Fail(Kind::BadRequest, format!("missing string field {name:?}")))
}

fn not_found(e: impl std::fmt::Display) -> Fail {
    Fail(Kind::NotFound, e.to_string())
}

fn failed(e: impl std::fmt::Display) -> Fail {
    Fail(Kind::Failed, e.to_string())
}

fn handle(
    gw: &Gateway,
    req: &Value,
    writers: &mut HashMap<(String, String), Box<dyn DynWriter>>,
) -> Result<Value, Fail> {
    let cmd = field(req, "cmd")?;
    let rt = gw.runtime();
    let component = || rt.component(field(req, "component")?).map_err(not_found);
    match cmd {
        "ls" => Ok(rt
            .components()
            .iter()
            .map(|t| json!({"name": t.name(), "state": t.state()}))
            .collect()),
        "devices" => Ok(serde_json::to_value(rt.registry().entries()).unwrap_or(Value::Null)),
        "status" => Ok(status(gw)),
        "describe" => {
            let t = component()?;
            Ok(json!({
                "name": t.name(),
                "state": t.state(),
                "ports": t.ports(),
                "operations": t.operations(),
                "properties": t.properties().list(),
                "attributes": t.attributes().list(),
                "counters": t.counters(),
                "activity": t.stats(),
            }))
        }
        "get" => {
            let t = component()?;
            if let Some(port) = req.get("port").and_then(Value::as_str) {
                let p = t.port(port).map_err(not_found)?;
                p.last_value()
                    .map_err(failed)
                    .map(|v| v.unwrap_or(Value::Null))
            } else if let Some(prop) = req.get("property").and_then(Value::as_str) {
                t.properties().get_value(prop).map_err(not_found)
            } else {
                Err(Fail(
                    Kind::BadRequest,
                    "get needs \"port\" or \"property\"".into(),
                ))
            }
        }
        "set" => {
            let t = component()?;
            let value = req
                .get("value")
                .cloned()
                .ok_or_else(|| Fail(Kind::BadRequest, "set needs \"value\"".into()))?;
            if let Some(port) = req.get("port").and_then(Value::as_str) {
                let key = (t.name().to_string(), port.to_string());
                if !writers.contains_key(&key) {
                    let p = t.port(port).map_err(not_found)?;
                    writers.insert(
                        key.clone(),
                        p.writer(ConnPolicy::buffer(16)).map_err(failed)?,
                    );
                }
                match writers.get_mut(&key) {
                    Some(w) => w.write(value).map_err(failed).map(|()| Value::Null),
                    None => Err(failed("writer vanished")),
                }
            } else if let Some(prop) = req.get("property").and_then(Value::as_str) {
                t.properties()
                    .set_value(prop, value)
                    .map_err(failed)
                    .map(|()| Value::Null)
            } else {
                Err(Fail(
                    Kind::BadRequest,
                    "set needs \"port\" or \"property\"".into(),
                ))
            }
        }
        "call" => {
            let t = component()?;
            let op = field(req, "operation")?;
            let args = match req.get("args") {
                None => Vec::new(),
                Some(Value::Array(a)) => a.clone(),
                Some(_) => return Err(Fail(Kind::BadRequest, "\"args\" must be an array".into())),
            };
            t.call_value(op, args).map_err(|e| match e {
                rtt::component::CallOrIntrospect::Introspect(e) => not_found(e),
                rtt::component::CallOrIntrospect::Call(e) => failed(e),
            })
        }
        "configure" | "start" | "stop" | "cleanup" | "recover" => {
            let t = component()?;
            let r = match cmd {
                "configure" => t.configure(),
                "start" => t.start(),
                "stop" => t.stop(),
                "cleanup" => t.cleanup(),
                _ => t.recover(),
            };
            r.map_err(failed).map(|()| json!(t.state()))
        }
        other => Err(Fail(
            Kind::UnknownCommand,
            format!(
                "unknown command {other:?}; commands: ls, describe, devices, get, set, call, configure, start, stop, cleanup, recover"
            ),
        )),
    }
}

/// A reply's outcome: the `ok` value, or the `error` message.
pub fn outcome(reply: &Value) -> Result<Value, String> {
    match (reply.get("ok"), reply.get("error")) {
        (Some(v), _) => Ok(v.clone()),
        (_, Some(e)) => Err(e
            .get("message")
            .and_then(Value::as_str)
            .unwrap_or("error")
            .to_string()),
        _ => Err(format!("unexpected reply: {reply}")),
    }
}

/// One request to a running gateway: sends `request` (an `id` is added if missing) and
/// returns the reply.
pub fn request(path: &Path, mut request: Value) -> std::io::Result<Value> {
    if let Value::Object(m) = &mut request {
        m.entry("id").or_insert(json!(1));
    }
    let mut conn = UnixStream::connect(path)?;
    let mut line = request.to_string();
    line.push('\n');
    conn.write_all(line.as_bytes())?;
    let mut reply = String::new();
    BufReader::new(conn).read_line(&mut reply)?;
    serde_json::from_str(&reply)
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
}

/// Sends `request` and hands every reply line to `each` until it returns false (then
/// `Ok(false)`) or the server closes the stream (`Ok(true)`).
pub fn stream(
    path: &Path,
    request: Value,
    mut each: impl FnMut(&Value) -> bool,
) -> std::io::Result<bool> {
    let mut conn = UnixStream::connect(path)?;
    let mut line = request.to_string();
    line.push('\n');
    conn.write_all(line.as_bytes())?;
    for line in BufReader::new(conn).lines() {
        let v: Value = serde_json::from_str(&line?)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))?;
        if !each(&v) {
            return Ok(false);
        }
    }
    Ok(true)
}
