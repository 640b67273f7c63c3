//! The `[zenoh]` section in the gateway: the node built with the deployment (its imported
//! devices registered, with IO components like a card's; its exported ports; connections
//! from other gateways' ports), started with the servers. Control requests for other
//! gateways: [`crate::forward`].
//!
//! Built without the `zenoh` feature, a `[zenoh]` section is refused by name.

/// The node type, or a stand-in of a build without the `zenoh` feature.
#[cfg(feature = "zenoh")]
pub type Node = scaleout::Node;

/// A build without Zenoh has no node.
#[cfg(not(feature = "zenoh"))]
pub enum Node {}

use crate::config::ZenohSection as Section;

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
        .map_err(|e| vec![("import".to_string(), e.to_string())])
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
    return (gw != node.name() && scaleout::config::is_gateway_name(gw))
        .then_some((gw, rest, port));
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = (gw, rest, port);
        match *node {}
    }
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

/// The components whose ports the `[zenoh]` section of `d` exports (through `node`, when
/// the gateway has one): a reload leaves them as they run.
pub(crate) fn exported_components(
    node: Option<&Node>,
    d: &crate::config::Deployment,
) -> std::collections::HashSet<String> {
    #[cfg(feature = "zenoh")]
    if let (Some(_), Some(section)) = (node, &d.zenoh) {
        return section
            .export
            .iter()
            .flat_map(|e| {
                let component = crate::config::split_port(e).map_or(e.as_str(), |(c, _)| c);
                [e.clone(), component.to_string()]
            })
            .collect();
    }
    let _ = (node, d);
    std::collections::HashSet::new()
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
