//! An [`HttpServer`] as a server of the deployment (`driver_api::Server`): started and
//! stopped with the gateway's servers, its counters in `hwgw status`, its health in the
//! gateway's.

use crate::config;
use crate::http::{self, HttpServer, Limits};
use driver_api::{CardStatus, ControlError, ControlLink, Server, ServerError};
use hyper::{Response, StatusCode};
use protocol::StatusReport;
use serde_json::{Value, json};
use std::sync::Arc;

/// What starts and stops with a server beside its connections (a thread of its own).
pub(crate) trait Hooks: Send + Sync {
    /// The server started.
    fn started(&self) -> std::io::Result<()>;
    /// The server stopped.
    fn stopped(&self);
}

/// An [`HttpServer`] as a server of the deployment.
pub(crate) struct HttpService {
    name: String,
    http: HttpServer,
    /// More of its state for `hwgw status` (the page's live streams).
    extra: Option<Box<dyn Fn() -> serde_json::Map<String, Value> + Send + Sync>>,
    /// What starts and stops with it.
    hooks: Option<Arc<dyn Hooks>>,
}

impl HttpService {
    pub(crate) fn new(
        name: &str,
        listen: std::net::SocketAddr,
        clients: usize,
        hosts: &[String],
        handler: http::Handler,
    ) -> HttpService {
        let limits = Limits {
            clients,
            head_timeout: config::HEAD_TIMEOUT,
            max_head_bytes: config::MAX_HEAD,
            hosts: hosts.into(),
        };
        let thread = format!("hwgw-{}", name.rsplit('.').next().unwrap_or(name));
        HttpService {
            name: name.to_string(),
            http: HttpServer::new(&thread, listen, limits, handler),
            extra: None,
            hooks: None,
        }
    }

    /// Runs `hooks` when it starts and stops.
    pub(crate) fn with_hooks(mut self, hooks: Arc<dyn Hooks>) -> Self {
        self.hooks = Some(hooks);
        self
    }

    pub(crate) fn with_status(
        mut self,
        extra: impl Fn() -> serde_json::Map<String, Value> + Send + Sync + 'static,
    ) -> Self {
        self.extra = Some(Box::new(extra));
        self
    }

    pub(crate) fn with_background(mut self, task: http::Background) -> Self {
        self.http.set_background(task);
        self
    }
}

impl Server for HttpService {
    fn name(&self) -> &str {
        &self.name
    }

    fn start(&self) -> Result<String, ServerError> {
        let listen = |source| ServerError::Listen {
            address: self.http.listen().to_string(),
            source,
        };
        let address = self.http.start().map_err(listen)?;
        if let Some(h) = &self.hooks
            && let Err(e) = h.started()
        {
            self.http.stop();
            return Err(listen(e));
        }
        Ok(address.to_string())
    }

    fn stop(&self) {
        self.http.stop();
        if let Some(h) = &self.hooks {
            h.stopped();
        }
    }

    fn address(&self) -> Option<String> {
        self.http.address().map(|a| a.to_string())
    }

    fn status(&self) -> Option<CardStatus> {
        let mut s = CardStatus::new(
            self.address().unwrap_or_else(|| "not started".into()),
            &self.http.stats().snapshot(),
        );
        if let Some(extra) = &self.extra {
            s.counters.extend(extra());
        }
        Some(s)
    }

    fn health(&self) -> Result<(), ServerError> {
        if self.http.alive() {
            Ok(())
        } else {
            Err(ServerError::NotStarted(format!(
                "{} (its thread ended)",
                self.name
            )))
        }
    }
}

impl Drop for HttpService {
    fn drop(&mut self) {
        self.stop();
    }
}

/// What `hwgw status` says, or why there is nothing.
pub(crate) fn status(control: &ControlLink) -> Result<StatusReport, ControlError> {
    let v = control.request(json!({"cmd": "status"}))?;
    serde_json::from_value(v).map_err(|e| ControlError::new("failed", format!("status: {e}")))
}

/// `/health`: 200 while healthy, 503 with the reasons when not.
pub(crate) fn health(control: &ControlLink) -> Response<http::Body> {
    let s = match status(control) {
        Ok(s) => s,
        Err(e) => {
            let body = json!({"health": "unavailable", "reasons": [e.to_string()]});
            return http::json(StatusCode::SERVICE_UNAVAILABLE, &body);
        }
    };
    if s.health == "ok" {
        return http::json(StatusCode::OK, &json!({"health": "ok"}));
    }
    let reasons: Vec<Value> = s.health.split("; ").map(Value::from).collect();
    http::json(
        StatusCode::SERVICE_UNAVAILABLE,
        &json!({"health": "unhealthy", "reasons": reasons}),
    )
}
