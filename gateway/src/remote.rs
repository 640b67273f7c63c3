//! The `[zenoh]` section in the gateway: the node built with the deployment (its imported
//! devices registered, with IO components like a card's), started with the servers, and
//! control requests for other gateways forwarded to them.
//!
//! A request whose component is `<gateway>/<component>` — and is no component here — goes
//! to that gateway through Zenoh (`hwgw get B/sim0.ai ch1`, `hwgw call B/follow …`),
//! with its answer or error as that gateway gave it; `ls` with `all` lists every
//! gateway's components, each under its gateway's name. Streams (`watch`, `record`) are not
//! forwarded: they are refused with a clear error.
//!
//! Built without the `zenoh` feature, a `[zenoh]` section is refused by name.

use crate::protocol::{ErrorKind, Request};
use crate::requests::Fail;
use serde_json::Value;

/// The node type, or a stand-in of a build without the `zenoh` feature.
#[cfg(feature = "zenoh")]
pub type Node = scaleout::Node;

/// A build without Zenoh has no node.
#[cfg(not(feature = "zenoh"))]
pub enum Node {}

/// What the deployment's `[zenoh]` section is in this build.
#[cfg(feature = "zenoh")]
pub type Section = scaleout::ZenohConfig;

/// What the deployment's `[zenoh]` section is in this build.
#[cfg(not(feature = "zenoh"))]
pub type Section = toml::Value;

/// The node of the deployment's `[zenoh]` section (its imported devices registered in
/// `registry`), or the problems as `(key under zenoh, message)`.
#[cfg(feature = "zenoh")]
pub(crate) fn node(
    section: &Section,
    base: &std::path::Path,
    registry: &std::sync::Arc<device_interface::Registry>,
) -> Result<std::sync::Arc<Node>, Vec<(String, String)>> {
    let problems = section.check(base);
    if !problems.is_empty() {
        return Err(problems);
    }
    let mut cfg = section.clone();
    if let Some(tls) = cfg.tls.as_mut() {
        tls.root_ca = base.join(&tls.root_ca);
        tls.cert = tls.cert.as_ref().map(|p| base.join(p));
        tls.key = tls.key.as_ref().map(|p| base.join(p));
    }
    Node::new(cfg, registry.clone())
        .map(std::sync::Arc::new)
        .map_err(|e| vec![("import".to_string(), e)])
}

/// A build without Zenoh refuses the section.
#[cfg(not(feature = "zenoh"))]
pub(crate) fn node(
    _: &Section,
    _: &std::path::Path,
    _: &std::sync::Arc<device_interface::Registry>,
) -> Result<std::sync::Arc<Node>, Vec<(String, String)>> {
    Err(vec![(
        String::new(),
        "this hwgw was built without the `zenoh` feature".to_string(),
    )])
}

/// The section's publication period, ms, if set.
pub(crate) fn publish_ms(section: &Section) -> Option<f64> {
    #[cfg(feature = "zenoh")]
    return section.publish_ms;
    #[cfg(not(feature = "zenoh"))]
    section.get("publish_ms").and_then(toml::Value::as_float)
}

/// The registry owners of the node's imported devices (their IO components are built
/// as a card's).
pub(crate) fn import_owners(node: &Node) -> Vec<String> {
    #[cfg(feature = "zenoh")]
    return node.import_owners();
    #[cfg(not(feature = "zenoh"))]
    match *node {}
}

/// The node as one of the gateway's servers.
pub(crate) fn server(node: &std::sync::Arc<Node>) -> Box<dyn driver_api::Server> {
    #[cfg(feature = "zenoh")]
    return Box::new(scaleout::NodeServer(node.clone()));
    #[cfg(not(feature = "zenoh"))]
    match **node {}
}

/// The remote end of a connection's `from` (`B/follow.out`): `(gateway, component,
/// port)`, when its component is not one of this gateway's but names another gateway.
pub(crate) fn remote_source<'a>(
    node: Option<&Node>,
    local: &dyn Fn(&str) -> bool,
    from: &'a str,
) -> Option<(&'a str, &'a str, &'a str)> {
    let node = node?;
    let (component, port) = crate::config::split_port(from)?;
    if local(component) {
        return None;
    }
    let (gw, rest) = component.split_once('/')?;
    #[cfg(feature = "zenoh")]
    let other = gw != node.name() && scaleout::config::is_gateway_name(gw);
    #[cfg(not(feature = "zenoh"))]
    let other = match *node {};
    other.then_some((gw, rest, port))
}

/// Feeds local input port `to` (through `writer`, made with the connection's policy)
/// from port `port` of component `component` of gateway `gw`.
pub(crate) fn link(
    node: &Node,
    (gw, component, port): (&str, &str, &str),
    writer: Box<dyn rtt::component::DynWriter>,
    label: String,
) {
    #[cfg(feature = "zenoh")]
    node.link(scaleout::ports::Link::new(
        gw, component, port, writer, label,
    ));
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = (gw, component, port, writer, label);
        match *node {}
    }
}

/// Exports the output ports the section names (`component.port` or `component`); the
/// problems as `(key under zenoh, message)`.
pub(crate) fn exports(
    node: &Node,
    section: &Section,
    runtime: &rtt::Runtime,
) -> Vec<(String, String)> {
    #[cfg(feature = "zenoh")]
    {
        use rtt::component::Direction;
        use rtt::port::ConnPolicy;
        let mut problems = Vec::new();
        for (i, name) in section.export.iter().enumerate() {
            let (component, only) = match runtime.component(name) {
                Ok(_) => (name.as_str(), None),
                Err(_) => match crate::config::split_port(name) {
                    Some((c, p)) => (c, Some(p)),
                    None => (name.as_str(), None),
                },
            };
            let ports = runtime.component(component).map(|t| {
                let outs: Vec<String> = t
                    .ports()
                    .into_iter()
                    .filter(|p| p.direction == Direction::Output)
                    .map(|p| p.name)
                    .filter(|p| only.is_none_or(|o| o == p))
                    .collect();
                (t, outs)
            });
            let (t, outs) = match ports {
                Ok((_, outs)) if outs.is_empty() => {
                    problems.push((
                        format!("export[{i}]"),
                        format!("{name:?}: no output port of that name to export"),
                    ));
                    continue;
                }
                Ok(x) => x,
                Err(e) => {
                    problems.push((format!("export[{i}]"), e.to_string()));
                    continue;
                }
            };
            for p in outs {
                let reader = t.port(&p).map_err(|e| e.to_string()).and_then(|port| {
                    port.stamped_reader(ConnPolicy::buffer(scaleout::config::EXPORT_BUFFER))
                        .map_err(|e| e.to_string())
                });
                match reader {
                    Ok(r) => node.export(scaleout::ports::Export::new(
                        node.name(),
                        component,
                        &p,
                        r,
                        scaleout::config::EXPORT_BUFFER,
                    )),
                    Err(e) => problems.push((format!("export[{i}]"), e)),
                }
            }
        }
        problems
    }
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = (section, runtime);
        match *node {}
    }
}

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
        | Request::Watch { component, .. } => Some(component),
        Request::Ls { .. } | Request::Devices | Request::Status | Request::Record { .. } => None,
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
fn body(gw: &str, mut reply: Value) -> Result<Value, Fail> {
    if let Some(ok) = reply.get_mut("ok") {
        return Ok(ok.take());
    }
    let kind = reply["error"]["kind"].clone();
    let message = reply["error"]["message"].as_str().unwrap_or("").to_string();
    let kind = serde_json::from_value(kind).unwrap_or(ErrorKind::Failed);
    Err(Fail(kind, format!("{gw}: {message}")))
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
    let gateways = node
        .gateways()
        .map_err(|e| Fail(ErrorKind::Failed, e.to_string()))?;
    let others = gateways
        .iter()
        .filter(|g| g.gateway != node.name() && scaleout::config::is_gateway_name(&g.gateway));
    for g in others {
        match node.request(&g.gateway, &serde_json::json!({"cmd": "ls"})) {
            Ok(reply) => match body(&g.gateway, reply) {
                Ok(v) => prefixed(&g.gateway, v, &mut all),
                Err(Fail(_, m)) => tracing::warn!("ls --all: {m}"),
            },
            Err(e) => tracing::warn!("ls --all: {}: {e}", g.gateway),
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
