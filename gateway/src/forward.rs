//! Control requests for other gateways: a request whose component is
//! `<gateway>/<component>` — and is no component here — goes to that gateway through Zenoh
//! (`hwgw get B/sim0.ai ch1`, `hwgw call B/follow …`), with its answer or error as that
//! gateway gave it; `ls` with `all` lists every gateway's components, each under its
//! gateway's name. Streams (`watch`, `record`) are not forwarded: they are refused with a
//! clear error. A request that came from another gateway is carried out here, never
//! forwarded again.

use crate::protocol::{ErrorKind, Request};
use crate::remote::Node;
use crate::requests::Fail;
use serde_json::Value;

/// The component a request names, for forwarding.
fn component_of(req: &Request) -> Option<&str> {
    match req {
        Request::Describe { component }
        | Request::Get { component, .. }
        | Request::Set { component, .. }
        | Request::Call { component, .. }
        | Request::Configure { component }
        | Request::Start { component }
        | Request::Stop { component }
        | Request::Cleanup { component }
        | Request::Recover { component }
        | Request::Properties { component }
        | Request::LoadProperties { component, .. }
        | Request::Watch { component, .. } => Some(component),
        Request::Ls { .. }
        | Request::Devices
        | Request::Status
        | Request::Record { .. }
        | Request::Reload
        // The deployment is changed on its own gateway's host only.
        | Request::Load { .. }
        | Request::Unload { .. }
        | Request::Connect { .. }
        | Request::Disconnect { .. }
        | Request::SetPeriod { .. }
        | Request::SetPriority { .. }
        | Request::Changes
        | Request::Deployment
        | Request::Log { .. } => None,
    }
}

/// Carries out `req` at another gateway when it names one (`B/…`) or asks for every
/// gateway (`ls` with `all`); `None` when it is for this gateway alone.
///
/// `here` carries out a request at this gateway: a component named under this gateway's
/// own name (`A/follow` at A, as `ls --all` lists it) is this gateway's.
pub(crate) fn forward(
    node: Option<&Node>,
    local: &dyn Fn(&str) -> bool,
    req: &Request,
    here: &dyn Fn(&Request) -> Result<Value, Fail>,
) -> Option<Result<Value, Fail>> {
    if let Request::Ls { all: true } = req {
        let Some(node) = node else {
            return Some(here(&Request::Ls { all: false }));
        };
        return Some(ls_all(node, &|| here(&Request::Ls { all: false })));
    }
    let c = component_of(req)?;
    if local(c) {
        return None;
    }
    let (gw, rest) = c.split_once('/')?;
    if !is_gateway(gw) {
        // `*/x` or `a b/x` name no gateway: never a key expression matching many.
        return None;
    }
    if node.is_some_and(|n| own_name(n) == gw) {
        let mut v = serde_json::to_value(req).ok()?;
        v["component"] = Value::String(rest.to_string());
        let req: Request = serde_json::from_value(v).ok()?;
        return Some(here(&req));
    }
    let Some(node) = node else {
        return Some(Err(Fail(
            ErrorKind::NotFound,
            format!(
                "no component {c:?}; {gw:?} would be another gateway, but this one has no [zenoh] section"
            ),
        )));
    };
    if matches!(req, Request::Watch { .. }) {
        return Some(Err(Fail(
            ErrorKind::BadRequest,
            format!(
                "watch streams are not forwarded to gateway {gw:?}: run hwgw watch on its host, or import its devices"
            ),
        )));
    }
    let mut v = match serde_json::to_value(req) {
        Ok(v) => v,
        Err(e) => return Some(Err(Fail(ErrorKind::Failed, e.to_string()))),
    };
    v["component"] = Value::String(rest.to_string());
    Some(ask(node, gw, &v))
}

/// True when `gw` can be a gateway's name.
fn is_gateway(gw: &str) -> bool {
    #[cfg(feature = "zenoh")]
    return scaleout::config::is_gateway_name(gw);
    #[cfg(not(feature = "zenoh"))]
    !gw.is_empty()
}

/// This gateway's name in the name space.
fn own_name(node: &Node) -> &str {
    #[cfg(feature = "zenoh")]
    return node.name();
    #[cfg(not(feature = "zenoh"))]
    match *node {}
}

#[cfg(feature = "zenoh")]
fn ask(node: &Node, gw: &str, request: &Value) -> Result<Value, Fail> {
    let reply = node
        .request(gw, request)
        .map_err(|e| Fail(ErrorKind::Failed, e.to_string()))?;
    body(gw, reply)
}

#[cfg(not(feature = "zenoh"))]
fn ask(node: &Node, _: &str, _: &Value) -> Result<Value, Fail> {
    match *node {}
}

/// A forwarded reply's body (`{"ok": …}` or `{"error": …}`) as this gateway's answer.
#[cfg_attr(
    not(feature = "zenoh"),
    allow(dead_code, reason = "only forwarded replies have a body")
)]
pub(crate) fn body(gw: &str, reply: Value) -> Result<Value, Fail> {
    crate::protocol::reply_body(reply)
        .map_err(|(kind, message)| Fail(kind, format!("{gw}: {message}")))
}

#[cfg(feature = "zenoh")]
fn ls_all(node: &Node, ls_here: &dyn Fn() -> Result<Value, Fail>) -> Result<Value, Fail> {
    let mut all = Vec::new();
    let prefixed = |gw: &str, v: Value, all: &mut Vec<Value>| {
        for mut e in v.as_array().cloned().unwrap_or_default() {
            // A peer's answer is not trusted to be what it should: what is not a
            // component entry is left out.
            let Some(o) = e.as_object_mut() else {
                continue;
            };
            let Some(name) = o.get("name").and_then(Value::as_str).map(str::to_string) else {
                continue;
            };
            o.insert("name".into(), Value::String(format!("{gw}/{name}")));
            all.push(e);
        }
    };
    prefixed(node.name(), ls_here()?, &mut all);
    // Those that answer the catalogue query, and those imported from (an answer lost on a
    // loaded link still leaves them asked).
    let mut names: Vec<String> = node
        .gateways()
        .map_err(|e| Fail(ErrorKind::Failed, e.to_string()))?
        .into_iter()
        .map(|g| g.gateway)
        .chain(node.imported_gateways())
        .filter(|g| g != node.name() && scaleout::config::is_gateway_name(g))
        .collect();
    names.sort();
    names.dedup();
    for g in &names {
        match node.request(g, &serde_json::json!({"cmd": "ls"})) {
            Ok(reply) => match body(g, reply) {
                Ok(v) => prefixed(g, v, &mut all),
                Err(Fail(_, m)) => tracing::warn!("ls --all: {m}"),
            },
            Err(e) => tracing::warn!("ls --all: {g}: {e}"),
        }
    }
    Ok(Value::Array(all))
}

#[cfg(not(feature = "zenoh"))]
fn ls_all(node: &Node, _: &dyn Fn() -> Result<Value, Fail>) -> Result<Value, Fail> {
    match *node {}
}

/// Lets other gateways send control requests: `handler` carries one out here.
pub(crate) fn serve_control(node: &Node, handler: impl Fn(Value) -> Value + Send + Sync + 'static) {
    #[cfg(feature = "zenoh")]
    node.set_control(std::sync::Arc::new(handler));
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = handler;
        match *node {}
    }
}
