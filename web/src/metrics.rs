//! `[server.metrics]`: `GET /metrics` (OpenMetrics text, [`crate::exposition`], to a
//! client that asks for it, as Prometheus does; else Prometheus' text format) and `GET
//! /health` (200 with `{"health": "ok"}` while the gateway is healthy, 503 with the
//! reasons when not: the rule that feeds systemd's watchdog).

use crate::config::{self, MetricsConfig, PortRef};
use crate::guard::Blocking;
use crate::http::{self, Answer, Routes};
use crate::service::{HttpService, health, status};
use driver_api::{CardError, ControlLink, Server, ServerContext};
use hyper::{Method, Request, Response, StatusCode};
use serde_json::json;
use std::sync::Arc;

/// The OpenMetrics text content type.
const OPENMETRICS: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";
/// Prometheus' text format, for a client that does not ask for OpenMetrics.
const PROMETHEUS_TEXT: &str = "text/plain; version=0.0.4; charset=utf-8";

/// Builds the metrics server of a `[server.metrics]` section.
pub fn build(
    c: &MetricsConfig,
    ctx: &mut ServerContext<'_>,
) -> Result<Box<dyn Server>, Vec<CardError>> {
    let mut problems = Vec::new();
    let endpoint = config::endpoint(&c.listen, c.max_clients, &mut problems);
    let ports = config::ports(&c.ports, ctx)
        .map_err(|p| problems.extend(p))
        .ok();
    let (Some((listen, clients)), Some(ports), true) = (endpoint, ports, problems.is_empty())
    else {
        return Err(problems);
    };
    let routes = Arc::new(MetricsRoutes {
        control: ctx.control().clone(),
        ports,
        pool: Blocking::new(),
    });
    let handler = http::Handler::Http(routes);
    let service = HttpService::new(ctx.name(), listen, clients, &c.hosts, handler);
    Ok(Box::new(service))
}

struct MetricsRoutes {
    control: ControlLink,
    ports: Vec<PortRef>,
    /// What the scrapes wait for the gateway in.
    pool: Blocking,
}

impl Routes for MetricsRoutes {
    fn route(self: Arc<Self>, req: Request<hyper::body::Incoming>) -> Answer {
        Box::pin(async move {
            if req.method() != Method::GET && req.method() != Method::HEAD {
                return http::text(StatusCode::METHOD_NOT_ALLOWED, "GET only\n");
            }
            match req.uri().path() {
                "/metrics" => {
                    let me = self.clone();
                    let openmetrics = req
                        .headers()
                        .get_all("accept")
                        .iter()
                        .filter_map(|v| v.to_str().ok())
                        .any(|v| v.contains("application/openmetrics-text"));
                    let pool = self.pool.clone();
                    http::busy_or(pool.try_run(move || me.metrics(openmetrics)).await)
                }
                "/health" => {
                    let control = self.control.clone();
                    http::busy_or(self.pool.try_run(move || health(&control)).await)
                }
                _ => http::text(StatusCode::NOT_FOUND, "/metrics or /health\n"),
            }
        })
    }
}

impl MetricsRoutes {
    /// The metrics in OpenMetrics text, or (`openmetrics` false) in Prometheus' text
    /// format.
    fn metrics(&self, openmetrics: bool) -> Response<http::Body> {
        let status = match status(&self.control) {
            Ok(s) => s,
            Err(e) => return http::text(StatusCode::SERVICE_UNAVAILABLE, format!("{e}\n")),
        };
        let values: Vec<_> = self
            .ports
            .iter()
            .filter_map(|p| {
                let request = json!({"cmd": "get", "component": p.component, "port": p.port});
                let v = self.control.request(request).ok()?;
                Some((p.component.clone(), p.port.clone(), v))
            })
            .collect();
        let text = crate::exposition::encode(&status, &values);
        if openmetrics {
            http::respond(StatusCode::OK, OPENMETRICS, text)
        } else {
            let text = crate::exposition::to_prometheus_text(&text);
            http::respond(StatusCode::OK, PROMETHEUS_TEXT, text)
        }
    }
}
