//! Server types by name: which top-level sections of a deployment are servers.
//!
//! A server is what hwgw serves beside its cards ([`driver_api::Server`]). A deployment
//! asks for one with a top-level table named after its type — `[modbus_server]` — and the
//! type's build function makes it from that section, parsed strictly where it stands (so
//! its errors point at the file, line and key, as a card's driver section's do), over the
//! device registry. A type may also be registered as `server.NAME`, asked for with a
//! table under the deployment's `[server]` (`[server.metrics]`): its deployment key is
//! then `server.NAME`. hwgw ships `modbus_server`; a user's binary adds its own with
//! [`ServerTypes::register`]. The gateway names no server type itself: a top-level key
//! (or a table under `[server]`) that is neither one of the deployment's own
//! ([`DEPLOYMENT_KEYS`]) nor a registered server is refused, with both lists.
//!
//! The Zenoh node (`[zenoh]`) is among the gateway's servers at run time too, but it is
//! not a plug-in: it is built before the cards' IO components (it registers the devices
//! it imports, and feeds connections from other gateways), so it keeps a section of its
//! own in [`Deployment`].

use crate::config::{DEPLOYMENT_KEYS, Deployment};
use crate::drivers::{SectionError, parse};
use crate::problems::{KeyPath, Problems};
use driver_api::{CardError, ControlLink, Server, ServerBuildFn, ServerContext};
use serde::de::DeserializeOwned;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use toml::Spanned;
use toml::de::DeValue;

/// Why a section did not make a server.
enum ServerProblem {
    /// The section does not parse into the server's section type.
    Section(SectionError),
    /// The server type refused it: every problem, at its key under the section.
    Refused(Vec<CardError>),
}

/// A server type with its section type erased.
trait ServerEntry: Send + Sync {
    /// Parses `section` and builds the server.
    fn build(
        &self,
        section: Spanned<DeValue<'_>>,
        ctx: &mut ServerContext<'_>,
    ) -> Result<Box<dyn Server>, ServerProblem>;
}

struct Typed<C>(ServerBuildFn<C>);

impl<C: DeserializeOwned + 'static> ServerEntry for Typed<C> {
    fn build(
        &self,
        section: Spanned<DeValue<'_>>,
        ctx: &mut ServerContext<'_>,
    ) -> Result<Box<dyn Server>, ServerProblem> {
        let config: C = parse(section).map_err(ServerProblem::Section)?;
        (self.0)(&config, ctx).map_err(ServerProblem::Refused)
    }
}

/// Server types by name: the top-level key of their section.
#[derive(Clone)]
pub struct ServerTypes {
    types: BTreeMap<String, Arc<dyn ServerEntry>>,
}

impl ServerTypes {
    /// No server types.
    pub fn empty() -> Self {
        ServerTypes {
            types: BTreeMap::new(),
        }
    }

    /// The server types built into hwgw: modbus_server, server.metrics (Prometheus),
    /// server.web (the web page), server.foxglove (the Foxglove live stream),
    /// server.mqtt (a Sparkplug B edge node and JSON topics) and server.opcua (an OPC UA
    /// server).
    pub fn builtin() -> Self {
        let mut t = Self::empty();
        t.register("modbus_server", driver_modbus::served::build);
        t.register("server.metrics", web::metrics::build);
        t.register("server.web", web::page::build);
        t.register("server.foxglove", web::foxglove::build);
        t.register("server.mqtt", mqtt::build);
        t.register("server.opcua", opcua::build);
        t
    }

    /// Adds server type `name`, built by `build` from the top-level section `[name]` (or,
    /// for a name `server.NAME`, from `[server.NAME]`; type `C`, parsed strictly); a name
    /// already taken, by another server type or by one of the deployment's own keys
    /// ([`DEPLOYMENT_KEYS`]), or `server` itself, is refused (returns false).
    pub fn register<C: DeserializeOwned + 'static>(
        &mut self,
        name: &str,
        build: ServerBuildFn<C>,
    ) -> bool {
        let nested = name.strip_prefix(NESTED).and_then(|n| n.strip_prefix('.'));
        if self.types.contains_key(name)
            || DEPLOYMENT_KEYS.contains(&name)
            || name == NESTED
            || nested.is_some_and(|n| n.is_empty() || n.contains('.'))
        {
            return false;
        }
        self.types.insert(name.to_string(), Arc::new(Typed(build)));
        true
    }

    /// The server type names, sorted.
    pub fn names(&self) -> Vec<&str> {
        self.types.keys().map(String::as_str).collect()
    }

    /// True when `name` is a server type of this build.
    pub fn contains(&self, name: &str) -> bool {
        self.types.contains_key(name)
    }
}

/// The top-level table whose tables are servers by their type's `server.NAME`.
pub const NESTED: &str = "server";

/// Every server section of `d`: its type name (`modbus_server`, `server.metrics`) and
/// where it stands; a `server` key that is not a table is a problem.
fn sections(d: &Deployment, problems: &mut Problems<'_, '_>) -> Vec<(String, KeyPath)> {
    let mut out = Vec::new();
    for (key, value) in &d.servers {
        if key != NESTED {
            out.push((key.clone(), KeyPath::top(key)));
            continue;
        }
        match value.as_table() {
            Some(t) => out.extend(
                t.keys()
                    .map(|k| (format!("{NESTED}.{k}"), KeyPath::top(NESTED).key(k))),
            ),
            None => problems.at(
                &KeyPath::top(NESTED),
                "[server] holds a table for each server: [server.NAME]",
            ),
        }
    }
    out
}

/// The server sections of `d` that are neither the deployment's own keys nor a server
/// type of `types`, each with what a deployment may have at the top: refused.
pub(crate) fn unknown_keys(d: &Deployment, types: &ServerTypes, problems: &mut Problems<'_, '_>) {
    for (key, at) in sections(d, problems) {
        if types.contains(&key) {
            continue;
        }
        let servers = match types.names() {
            names if names.is_empty() => "none".to_string(),
            names => names.join(", "),
        };
        let msg = format!(
            "unknown key {key:?}; a deployment has {}, and the servers of this build: {servers}",
            DEPLOYMENT_KEYS.join(", ")
        );
        problems.at_key(&at, msg);
    }
}

/// Builds the server of every server section of `d` (unknown keys are
/// [`unknown_keys`]'s), over the devices `runtime`'s registry holds, each given `control`;
/// files they name are relative to `base`. Problems go to `problems`, located under the
/// section.
pub(crate) fn build(
    d: &Deployment,
    types: &ServerTypes,
    (runtime, control): (&rtt::Runtime, &ControlLink),
    base: &Path,
    problems: &mut Problems<'_, '_>,
) -> Vec<Box<dyn Server>> {
    let mut servers = Vec::new();
    let mut quiet = Problems::new(problems.source());
    for (key, at) in sections(d, &mut quiet) {
        let Some(entry) = types.types.get(&key) else {
            continue;
        };
        let Some(section) = problems.source().value(&at) else {
            problems.at(&at, format!("[{key}] is not in the file"));
            continue;
        };
        let mut ctx = ServerContext::new(&key, runtime, base, control.clone());
        match entry.build(section.clone(), &mut ctx) {
            Ok(server) => servers.push(server),
            Err(ServerProblem::Section(SectionError::Parse {
                path,
                span,
                message,
            })) => problems.at_span(&at.join(&path), span, message),
            Err(ServerProblem::Section(SectionError::Card(e))) => {
                problems.at(&at.join(e.key.as_deref().unwrap_or("")), e.message);
            }
            Err(ServerProblem::Refused(list)) => {
                for e in list {
                    problems.at(&at.join(e.key.as_deref().unwrap_or("")), e.message);
                }
            }
        }
    }
    servers
}
