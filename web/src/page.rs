//! `[server.web]`: one page for a browser, compiled in (no build step, no external
//! asset: it works offline on a plant network), and the API it reads.
//!
//! | path | what |
//! |---|---|
//! | `GET /` | the page: devices with health and age, cards with counters, components with state and timing, live values of the listed ports with a plot each, the lateness histograms |
//! | `GET /app.js`, `GET /style.css`, `GET /icon.svg` | its script, style and icon |
//! | `GET /api/status` | what `hwgw status --json` says |
//! | `GET /api/ports` | the listed ports, and whether the page may write |
//! | `GET /api/live` | Server-Sent Events: the listed ports' values, at each change |
//! | `POST /api/set` | `{"component", "port", "value"}` with `Authorization: Bearer TOKEN`: a listed input port set as `hwgw set` sets it, only with `allow_writes` |
//! | `GET /health` | as the metrics server's |
//!
//! Every answer says not to be stored (the assets: revalidated), not to be sniffed or
//! framed; the page's Content-Security-Policy allows nothing but its own script, style
//! and API (no inline script, no eval).

use crate::config::{self, PortRef, WebConfig};
use crate::guard::Blocking;
use crate::http::{self, Answer, Routes};
use crate::sampler::Streams;
use crate::service::{HttpService, health};
use driver_api::{CardError, ControlLink, Server, ServerContext};
use hyper::{Method, Request, Response, StatusCode};
use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

const INDEX: &str = include_str!("../assets/index.html");
const SCRIPT: &str = include_str!("../assets/app.js");
const STYLE: &str = include_str!("../assets/style.css");
const ICON: &str = include_str!("../assets/icon.svg");

/// The page's Content-Security-Policy.
pub const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
connect-src 'self'; img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The largest `/api/set` body, bytes.
const MAX_SET_BODY: usize = 64 * 1024;

/// Builds the web server of a `[server.web]` section.
pub fn build(
    c: &WebConfig,
    ctx: &mut ServerContext<'_>,
) -> Result<Box<dyn Server>, Vec<CardError>> {
    let mut problems = Vec::new();
    let endpoint = config::endpoint(&c.listen, c.max_clients, &mut problems);
    if !(10..=10_000).contains(&c.sample_ms) {
        problems.push(CardError::at(
            "sample_ms",
            format!("{}: 10-10000 ms", c.sample_ms),
        ));
    }
    let token = config::token(&c.token, c.allow_writes, &mut problems);
    let ports = config::ports(&c.ports, ctx)
        .map_err(|p| problems.extend(p))
        .ok();
    let (Some((listen, clients)), Some(ports), true) = (endpoint, ports, problems.is_empty())
    else {
        return Err(problems);
    };
    let ports = Arc::new(ports);
    let streams = Arc::new(Streams::default());
    let routes = Arc::new(Page {
        control: ctx.control().clone(),
        ports: ports.clone(),
        writes: if c.allow_writes { token } else { None },
        streams: streams.clone(),
        refused_writes: AtomicU64::new(0),
        pool: Blocking::new(),
    });
    let (control, period) = (ctx.control().clone(), Duration::from_millis(c.sample_ms));
    let s = streams.clone();
    let counted = routes.clone();
    let handler = http::Handler::Http(routes);
    let service = HttpService::new(ctx.name(), listen, clients, &c.hosts, handler)
        .with_background(Arc::new(move || {
            Box::pin(crate::sampler::run(
                control.clone(),
                ports.clone(),
                period,
                s.clone(),
            ))
        }))
        .with_status(move || {
            let mut m = serde_json::Map::new();
            let load = |a: &AtomicU64| Value::from(a.load(Ordering::Relaxed));
            m.insert(
                "live_streams".into(),
                Value::from(counted.streams.listeners()),
            );
            m.insert("live_events".into(), load(&counted.streams.sent));
            m.insert("live_events_dropped".into(), load(&counted.streams.dropped));
            m.insert(
                "live_streams_ended_slow".into(),
                load(&counted.streams.ended_slow),
            );
            m.insert("writes_refused".into(), load(&counted.refused_writes));
            m
        });
    Ok(Box::new(service))
}

struct Page {
    control: ControlLink,
    ports: Arc<Vec<PortRef>>,
    /// The token a write must carry; `None`: the page is read-only.
    writes: Option<String>,
    streams: Arc<Streams>,
    refused_writes: AtomicU64,
    /// What requests wait for the gateway in.
    pool: Blocking,
}

impl Routes for Page {
    fn route(self: Arc<Self>, req: Request<hyper::body::Incoming>) -> Answer {
        Box::pin(async move {
            let get = req.method() == Method::GET || req.method() == Method::HEAD;
            match (get, req.method() == Method::POST, req.uri().path()) {
                (true, _, "/") => asset("text/html; charset=utf-8", INDEX),
                (true, _, "/app.js") => asset("text/javascript; charset=utf-8", SCRIPT),
                (true, _, "/style.css") => asset("text/css; charset=utf-8", STYLE),
                (true, _, "/icon.svg") => asset("image/svg+xml", ICON),
                (true, _, "/health") => {
                    let control = self.control.clone();
                    http::busy_or(self.pool.try_run(move || health(&control)).await)
                }
                (true, _, "/api/status") => {
                    let control = self.control.clone();
                    let answer = self.pool.try_run(move || {
                        match control.request(json!({"cmd": "status"})) {
                            Ok(v) => http::json(StatusCode::OK, &v),
                            Err(e) => http::text(StatusCode::SERVICE_UNAVAILABLE, e.to_string()),
                        }
                    });
                    http::busy_or(answer.await)
                }
                (true, _, "/api/ports") => http::json(
                    StatusCode::OK,
                    &json!({"ports": *self.ports, "writes": self.writes.is_some()}),
                ),
                (true, _, "/api/live") => self.live(),
                (_, true, "/api/set") => self.set(req).await,
                (
                    _,
                    _,
                    "/" | "/app.js" | "/style.css" | "/icon.svg" | "/health" | "/api/status"
                    | "/api/ports" | "/api/live" | "/api/set",
                ) => http::text(StatusCode::METHOD_NOT_ALLOWED, "method not allowed\n"),
                _ => http::text(StatusCode::NOT_FOUND, "not found\n"),
            }
        })
    }
}

/// A compiled-in asset with the page's policy; revalidated rather than stored.
fn asset(content_type: &str, body: &'static str) -> Response<http::Body> {
    let mut r = Response::new(http::full(body));
    http::headers(&mut r, content_type, "no-cache");
    r.headers_mut().insert(
        "content-security-policy",
        hyper::header::HeaderValue::from_static(CSP),
    );
    r
}

impl Page {
    fn live(&self) -> Response<http::Body> {
        let mut r = Response::new(self.streams.subscribe());
        http::headers(&mut r, "text/event-stream", "no-store");
        r
    }

    async fn set(self: Arc<Self>, req: Request<hyper::body::Incoming>) -> Response<http::Body> {
        let refuse = |status: StatusCode, why: &str| {
            self.refused_writes.fetch_add(1, Ordering::Relaxed);
            http::json(status, &json!({"error": why}))
        };
        let Some(token) = &self.writes else {
            return refuse(
                StatusCode::FORBIDDEN,
                "this page is read-only (allow_writes = false)",
            );
        };
        let given = req
            .headers()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if !given.is_some_and(|g| crate::guard::same(g.as_bytes(), token.as_bytes())) {
            return refuse(
                StatusCode::UNAUTHORIZED,
                "a write needs the deployment's token",
            );
        }
        let body = match http::read_body(req, MAX_SET_BODY).await {
            Ok(b) => b,
            Err(e) => return refuse(StatusCode::PAYLOAD_TOO_LARGE, &e.to_string()),
        };
        let ask: SetAsk = match serde_json::from_slice(&body) {
            Ok(a) => a,
            Err(e) => {
                return refuse(
                    StatusCode::BAD_REQUEST,
                    &format!("{{component, port, value}}: {e}"),
                );
            }
        };
        let listed = |p: &&PortRef| p.component == ask.component && p.port == ask.port;
        if !self.ports.iter().filter(|p| p.input).any(|p| listed(&p)) {
            return refuse(
                StatusCode::FORBIDDEN,
                "only the page's listed input ports are set",
            );
        }
        let control = self.control.clone();
        let me = self.clone();
        let pool = self.pool.clone();
        let answer = pool.try_run(move || {
            let request = json!({"cmd": "set", "component": ask.component, "port": ask.port, "value": ask.value});
            match control.request(request) {
                Ok(v) => http::json(StatusCode::OK, &json!({"ok": v})),
                Err(e) => {
                    me.refused_writes.fetch_add(1, Ordering::Relaxed);
                    let status = if e.kind == "not_found" { StatusCode::NOT_FOUND } else { StatusCode::UNPROCESSABLE_ENTITY };
                    http::json(status, &json!({"error": e.to_string()}))
                }
            }
        });
        match answer.await {
            Some(a) => a,
            None => refuse(
                StatusCode::SERVICE_UNAVAILABLE,
                "busy: too many requests under way",
            ),
        }
    }
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SetAsk {
    component: String,
    port: String,
    value: Value,
}
