//! The HTTP/1.1 server under hwgw's web servers (hyper): bounded in clients, in the size
//! of a request's head and in how long that head may take to arrive, with its counters;
//! what it answers is its [`Routes`]'.
//!
//! A connection past the client limit is answered `503` at once and closed, without being
//! read; a head larger than [`Limits::max_head_bytes`] is answered `431` by hyper; a head
//! not whole within [`Limits::head_timeout`] (slowloris) closes the connection, and so
//! does a write the client leaves unread for [`crate::guard::WRITE_STALL`]; a `Host` the
//! server does not answer to is refused with 421 ([`crate::guard::host_allowed`]). The
//! server runs on a thread of its own with a single-threaded tokio runtime: nothing of
//! it runs on a component's thread, and a request that must wait for the gateway (a
//! control request) waits on the runtime's blocking pool, never on the accept loop.

use bytes::Bytes;
use http_body_util::BodyExt;
use http_body_util::combinators::BoxBody;
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper::{Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use std::convert::Infallible;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// A response body: whole, or a stream (Server-Sent Events).
pub type Body = BoxBody<Bytes, Infallible>;

/// A route's answer, to come.
pub type Answer = Pin<Box<dyn Future<Output = Response<Body>> + Send>>;

/// What a server answers.
pub trait Routes: Send + Sync + 'static {
    /// The response to `req` (its body not read yet: a route that takes one reads it
    /// through [`read_body`], bounded).
    fn route(self: Arc<Self>, req: Request<hyper::body::Incoming>) -> Answer;
}

/// A connection's own protocol, for a server that speaks more than plain HTTP (the
/// Foxglove WebSocket server): it is handed each connection within the client limit.
pub trait Connections: Send + Sync + 'static {
    /// Serves `conn` until it ends.
    fn serve(self: Arc<Self>, conn: Conn) -> Pin<Box<dyn Future<Output = ()> + Send>>;
}

/// A connection as a server's handler gets it: its writes fail once stalled too long.
pub type Conn = crate::guard::Stalling<tokio::net::TcpStream>;

/// What a server does with a connection it takes.
#[derive(Clone)]
pub enum Handler {
    /// HTTP/1.1, answered by routes.
    Http(Arc<dyn Routes>),
    /// Its own protocol.
    Raw(Arc<dyn Connections>),
}

/// How much a server takes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Limits {
    /// Connections at once; one more is answered 503 and closed.
    pub clients: usize,
    /// A request's head (request line and headers) must be whole this long after the
    /// server began reading it.
    pub head_timeout: Duration,
    /// The largest head read, bytes (at least 8192: hyper's floor).
    pub max_head_bytes: usize,
    /// Host names it answers to besides addresses and `localhost`
    /// ([`crate::guard::host_allowed`]).
    pub hosts: Arc<[String]>,
}

/// A server's counters.
#[derive(Debug, Default)]
pub struct Stats {
    /// Connections taken.
    pub accepted: AtomicU64,
    /// Connections answered 503 for the client limit.
    pub refused: AtomicU64,
    /// Connections open now.
    pub connected: AtomicU64,
    /// Requests answered.
    pub requests: AtomicU64,
    /// Connections closed on a malformed or oversized request.
    pub bad_requests: AtomicU64,
    /// Connections closed because a request's head did not arrive in time.
    pub head_timeouts: AtomicU64,
    /// Accepts that failed (out of file descriptors: the loop backs off).
    pub accept_failures: AtomicU64,
    /// Connections closed because the client stopped reading what it was sent.
    pub write_stalls: Arc<AtomicU64>,
    /// Requests refused for a `Host` the server does not answer to.
    pub bad_hosts: AtomicU64,
}

impl Stats {
    /// A snapshot, for `hwgw status`.
    pub fn snapshot(&self) -> StatsSnapshot {
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        StatsSnapshot {
            accepted: load(&self.accepted),
            refused: load(&self.refused),
            connected: load(&self.connected),
            requests: load(&self.requests),
            bad_requests: load(&self.bad_requests),
            head_timeouts: load(&self.head_timeouts),
            accept_failures: load(&self.accept_failures),
            write_stalls: load(&self.write_stalls),
            bad_hosts: load(&self.bad_hosts),
        }
    }
}

/// [`Stats`] as numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[allow(missing_docs, reason = "the fields of Stats, documented there")]
pub struct StatsSnapshot {
    pub accepted: u64,
    pub refused: u64,
    pub connected: u64,
    pub requests: u64,
    pub bad_requests: u64,
    pub head_timeouts: u64,
    pub accept_failures: u64,
    pub write_stalls: u64,
    pub bad_hosts: u64,
}

/// A running server: its address, and how to stop it.
struct Running {
    address: SocketAddr,
    stop: tokio::sync::watch::Sender<bool>,
    thread: std::thread::JoinHandle<()>,
}

/// Work a server runs beside its connections while it serves (made anew at each start).
pub type Background = Arc<dyn Fn() -> Pin<Box<dyn Future<Output = ()> + Send>> + Send + Sync>;

/// An HTTP server: built with its address and routes, started and stopped with the
/// gateway's servers.
pub struct HttpServer {
    name: String,
    listen: SocketAddr,
    limits: Limits,
    handler: Handler,
    stats: Arc<Stats>,
    running: Mutex<Option<Running>>,
    background: Option<Background>,
}

impl HttpServer {
    /// A server named `name` (its thread's name) for `listen`, within `limits`, handing
    /// its connections to `handler`; nothing is bound before [`start`](Self::start).
    pub fn new(name: &str, listen: SocketAddr, limits: Limits, handler: Handler) -> HttpServer {
        HttpServer {
            name: name.to_string(),
            listen,
            limits,
            handler,
            stats: Arc::new(Stats::default()),
            running: Mutex::new(None),
            background: None,
        }
    }

    /// Runs `task` on the server's runtime while it serves (it ends with the server).
    pub fn set_background(&mut self, task: Background) {
        self.background = Some(task);
    }

    /// Where it is to listen.
    pub fn listen(&self) -> SocketAddr {
        self.listen
    }

    /// Its counters.
    pub fn stats(&self) -> &Arc<Stats> {
        &self.stats
    }

    /// Binds its address and serves from a thread of its own; returns where it listens.
    pub fn start(&self) -> std::io::Result<SocketAddr> {
        let mut running = rtt::lock(&self.running);
        if let Some(r) = running.as_ref() {
            return Ok(r.address);
        }
        let listener = std::net::TcpListener::bind(self.listen)?;
        listener.set_nonblocking(true)?;
        let address = listener.local_addr()?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .max_blocking_threads(4)
            .thread_name(format!("{}-blocking", self.name))
            .build()?;
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let (handler, stats, limits) = (
            self.handler.clone(),
            self.stats.clone(),
            self.limits.clone(),
        );
        let background = self.background.clone();
        let thread = std::thread::Builder::new()
            .name(self.name.clone())
            .spawn(move || {
                runtime.block_on(async move {
                    if let Some(task) = background {
                        tokio::spawn(task());
                    }
                    match tokio::net::TcpListener::from_std(listener) {
                        Ok(l) => accept_loop(l, handler, stats, limits, stopped).await,
                        Err(e) => tracing::error!("cannot serve HTTP on {address}: {e}"),
                    }
                });
            })?;
        *running = Some(Running {
            address,
            stop,
            thread,
        });
        Ok(address)
    }

    /// Where it listens, while running.
    pub fn address(&self) -> Option<SocketAddr> {
        rtt::lock(&self.running).as_ref().map(|r| r.address)
    }

    /// Stops serving: every connection closed, the thread joined. Idempotent.
    pub fn stop(&self) {
        let Some(r) = rtt::lock(&self.running).take() else {
            return;
        };
        let _ = r.stop.send(true);
        if r.thread.join().is_err() {
            tracing::error!("{}: its thread panicked", self.name);
        }
    }

    /// False once its thread ended by itself (it could not serve).
    pub fn alive(&self) -> bool {
        rtt::lock(&self.running)
            .as_ref()
            .is_none_or(|r| !r.thread.is_finished())
    }
}

impl Drop for HttpServer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// What a connection over the client limit is told before it is closed.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain\r\n\
content-length: 24\r\nretry-after: 1\r\nconnection: close\r\n\r\ntoo many clients: later\n";

async fn accept_loop(
    listener: tokio::net::TcpListener,
    handler: Handler,
    stats: Arc<Stats>,
    limits: Limits,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let slots = Arc::new(tokio::sync::Semaphore::new(limits.clients));
    let mut conns = tokio::task::JoinSet::new();
    loop {
        tokio::select! {
            _ = stop.changed() => break,
            Some(_) = conns.join_next(), if !conns.is_empty() => {}
            accepted = listener.accept() => match accepted {
                Ok((tcp, _)) => {
                    let Ok(slot) = slots.clone().try_acquire_owned() else {
                        stats.refused.fetch_add(1, Ordering::Relaxed);
                        // Not read, not waited for: a full socket buffer loses the words.
                        let _ = tcp.try_write(BUSY);
                        continue;
                    };
                    stats.accepted.fetch_add(1, Ordering::Relaxed);
                    let (handler, stats, limits) = (handler.clone(), stats.clone(), limits.clone());
                    conns.spawn(async move {
                        let _slot = slot;
                        stats.connected.fetch_add(1, Ordering::Relaxed);
                        let _connected = Connected(&stats.connected);
                        let _ = tcp.set_nodelay(true);
                        let conn = crate::guard::Stalling::new(tcp, stats.write_stalls.clone());
                        match handler {
                            Handler::Http(routes) => serve(conn, routes, &stats, &limits).await,
                            Handler::Raw(c) => c.serve(conn).await,
                        }
                    });
                }
                Err(e) => {
                    stats.accept_failures.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!("HTTP accept failed: {e}; backing off");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
        }
    }
    conns.abort_all();
    while conns.join_next().await.is_some() {}
}

/// Counts a connection open while it lives.
struct Connected<'a>(&'a AtomicU64);

impl Drop for Connected<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

async fn serve(conn: Conn, routes: Arc<dyn Routes>, stats: &Arc<Stats>, l: &Limits) {
    let counted = stats.clone();
    let hosts = l.hosts.clone();
    let service = service_fn(move |req: Request<hyper::body::Incoming>| {
        counted.requests.fetch_add(1, Ordering::Relaxed);
        let host = req.headers().get("host").map(|h| h.to_str().unwrap_or(""));
        let answer = if crate::guard::host_allowed(host, &hosts) {
            routes.clone().route(req)
        } else {
            counted.bad_hosts.fetch_add(1, Ordering::Relaxed);
            let refused = text(
                StatusCode::MISDIRECTED_REQUEST,
                "this server answers to its address, localhost and its configured hosts\n",
            );
            Box::pin(async move { refused })
        };
        async move { Ok::<_, Infallible>(answer.await) }
    });
    let result = http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(l.head_timeout)
        .max_buf_size(l.max_head_bytes.max(8192))
        .serve_connection(TokioIo::new(conn), service)
        .await;
    if let Err(e) = result {
        if e.is_timeout() {
            stats.head_timeouts.fetch_add(1, Ordering::Relaxed);
        } else if e.is_parse() || e.is_parse_too_large() {
            stats.bad_requests.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// A whole body of `bytes`.
pub fn full(bytes: impl Into<Bytes>) -> Body {
    http_body_util::Full::new(bytes.into()).boxed()
}

/// A response of `status` with `content_type` and `body`, with the headers every answer
/// carries ([`headers`]).
pub fn respond(status: StatusCode, content_type: &str, body: impl Into<Bytes>) -> Response<Body> {
    let mut r = Response::new(full(body));
    *r.status_mut() = status;
    headers(&mut r, content_type, "no-store");
    r
}

/// Sets `content_type`, `cache` (Cache-Control) and what every answer says: not to be
/// sniffed, not to be framed, no referrer.
pub fn headers(r: &mut Response<Body>, content_type: &str, cache: &str) {
    let h = r.headers_mut();
    for (k, v) in [
        ("content-type", content_type),
        ("cache-control", cache),
        ("x-content-type-options", "nosniff"),
        ("x-frame-options", "DENY"),
        ("referrer-policy", "no-referrer"),
    ] {
        if let Ok(v) = hyper::header::HeaderValue::from_str(v) {
            h.insert(k, v);
        }
    }
}

/// The answer, or 503 when there was none for want of a free permit (too many requests
/// under way, [`crate::guard::Blocking`]).
pub fn busy_or(answer: Option<Response<Body>>) -> Response<Body> {
    answer.unwrap_or_else(|| {
        text(
            StatusCode::SERVICE_UNAVAILABLE,
            "busy: too many requests under way\n",
        )
    })
}

/// A plain-text answer of `status`.
pub fn text(status: StatusCode, body: impl Into<String>) -> Response<Body> {
    respond(status, "text/plain; charset=utf-8", body.into())
}

/// A JSON answer of `status` (floats as they round-trip).
pub fn json(status: StatusCode, value: &serde_json::Value) -> Response<Body> {
    respond(status, "application/json", value.to_string())
}

/// Why a request's body was not read.
#[derive(Debug, thiserror::Error)]
pub enum BodyError {
    /// It is longer than the route takes.
    #[error("the body is longer than {0} bytes")]
    TooLong(usize),
    /// The connection failed while it was read.
    #[error("reading the body failed: {0}")]
    Read(String),
}

/// `req`'s body, at most `limit` bytes.
pub async fn read_body(
    req: Request<hyper::body::Incoming>,
    limit: usize,
) -> Result<Bytes, BodyError> {
    let limited = http_body_util::Limited::new(req.into_body(), limit);
    match limited.collect().await {
        Ok(c) => Ok(c.to_bytes()),
        Err(e) if e.is::<http_body_util::LengthLimitError>() => Err(BodyError::TooLong(limit)),
        Err(e) => Err(BodyError::Read(e.to_string())),
    }
}
