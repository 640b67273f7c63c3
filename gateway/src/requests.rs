//! What each control request does: the commands of [`crate::protocol`] carried out on a
//! gateway.

use crate::deploy::Gateway;
use crate::protocol::{
    ComponentEntry, ComponentStatus, ControlReport, Description, DeviceStatus, ErrorKind,
    PortEntry, Request, StatusReport, Target,
};
use rtt::component::DynWriter;
use rtt::port::ConnPolicy;
use serde_json::Value;
use std::collections::HashMap;

/// Every device's health, every card's bus counters, and every component's state and
/// activity figures.
fn status(gw: &Gateway, control: ControlReport) -> StatusReport {
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
            let trimmed = |h: &[u64]| {
                let len = h.iter().rposition(|&n| n != 0).map_or(0, |i| i + 1);
                h[..len].to_vec()
            };
            ComponentStatus {
                name: t.name().to_string(),
                state: t.state(),
                steps: s.steps,
                overruns: s.overruns,
                healthy: s.healthy,
                unhealthy_spells: s.unhealthy_spells,
                unhealthy_ns: s.unhealthy_ns,
                realtime: s.realtime,
                lateness_p99_us: s.lateness_quantile(0.99).as_secs_f64() * 1e6,
                step_mean_us: s.step_mean().as_secs_f64() * 1e6,
                lateness_histogram: trimmed(&s.lateness_histogram),
                lateness_total_ns: s.lateness_total_ns,
                step_histogram: trimmed(&s.step_histogram),
                step_total_ns: s.step_total_ns,
                counters: t.counters(),
            }
        })
        .collect();
    StatusReport {
        health: gw.health().err().unwrap_or_else(|| "ok".into()),
        devices,
        cards: gw.card_status(),
        servers: gw.server_status(),
        components,
        control,
    }
}

/// Why a request failed: its kind and message.
pub(crate) struct Fail(pub(crate) ErrorKind, pub(crate) String);

pub(crate) fn not_found(e: impl std::fmt::Display) -> Fail {
    Fail(ErrorKind::NotFound, e.to_string())
}

pub(crate) fn failed(e: impl std::fmt::Display) -> Fail {
    Fail(ErrorKind::Failed, e.to_string())
}

fn to_value(v: impl serde::Serialize) -> Result<Value, Fail> {
    serde_json::to_value(v).map_err(failed)
}

pub(crate) fn handle(
    gw: &Gateway,
    control: ControlReport,
    req: &Request,
    writers: &mut HashMap<(String, String), Box<dyn DynWriter>>,
) -> Result<Value, Fail> {
    let rt = gw.runtime();
    let component = |name: &str| rt.component(name).map_err(not_found);
    match req {
        Request::Ls { .. } => to_value(
            rt.components()
                .iter()
                .map(|t| ComponentEntry {
                    name: t.name().to_string(),
                    state: t.state(),
                    warning: t.counters().warning,
                })
                .collect::<Vec<_>>(),
        ),
        Request::Devices => to_value(rt.registry().entries()),
        Request::Status => to_value(status(gw, control)),
        Request::Describe { component: c } => {
            let t = component(c)?;
            to_value(Description {
                name: t.name().to_string(),
                state: t.state(),
                ports: t
                    .ports()
                    .into_iter()
                    .map(|info| PortEntry {
                        connections: t.port(&info.name).map_or(0, |p| p.connections().len()),
                        info,
                    })
                    .collect(),
                operations: t.operations(),
                properties: t.properties().list(),
                attributes: t.attributes().list(),
                counters: t.counters(),
                activity: t.stats(),
                provides: t.provided(),
                requires: t.required(),
                peers: t.peer_aliases(),
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
        Request::Set {
            component: c,
            target: Target::Port(port),
            value,
        } => set_port(&component(c)?, port, value, writers),
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
        Request::Reload => {
            let report = gw.reload();
            crate::reload::log_reload("reload", &report);
            to_value(report)
        }
        Request::Load { .. }
        | Request::Unload { .. }
        | Request::Connect { .. }
        | Request::Disconnect { .. }
        | Request::SetPeriod { .. }
        | Request::SetPriority { .. }
        | Request::Changes
        | Request::Deployment => change(gw, req),
        Request::Get {
            component: c,
            target: Target::Property(_) | Target::Attribute(_),
        }
        | Request::Set {
            component: c,
            target: Target::Property(_) | Target::Attribute(_),
            ..
        }
        | Request::Properties { component: c }
        | Request::LoadProperties { component: c, .. } => values(&component(c)?, req),
        Request::Log { component, level } => log_levels(component.as_deref(), *level),
        Request::Watch { .. } | Request::Record { .. } => Err(Fail(
            ErrorKind::BadRequest,
            format!("{} streams: it is served on its own", req.cmd()),
        )),
    }
}

/// `set` of input port `port` of `t`: a device output is written now and answered with
/// what became of the write; any other input port gets the value through a writer of the
/// client's own (kept in `writers`).
fn set_port(
    t: &rtt::TaskContext,
    port: &str,
    value: &Value,
    writers: &mut HashMap<(String, String), Box<dyn DynWriter>>,
) -> Result<Value, Fail> {
    let p = t.port(port).map_err(not_found)?;
    if p.drives() {
        let state = t.state();
        if state != rtt::TaskState::Running {
            return Err(failed(format!(
                "component {:?} is {state:?}: its outputs are not driven now, so the value \
                 would never be written (start it first)",
                t.name()
            )));
        }
        return match p.drive(value.clone()) {
            Some(r) => r.map_err(failed).map(|()| Value::Null),
            None => Err(failed("port stopped driving")),
        };
    }
    let key = (t.name().to_string(), port.to_string());
    if !writers.contains_key(&key) {
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

/// The real-time log's levels, `component`'s set to `level` first when both are given.
fn log_levels(component: Option<&str>, level: Option<rtt::log::Level>) -> Result<Value, Fail> {
    match (component, level) {
        (Some(c), Some(l)) => {
            rtt::log::set_level(c, l).map_err(not_found)?;
        }
        (None, Some(_)) => {
            return Err(Fail(
                ErrorKind::BadRequest,
                "a level needs the component whose level it is".into(),
            ));
        }
        _ => {}
    }
    let areas: Vec<crate::protocol::LogArea> = match component {
        Some(c) => vec![crate::protocol::LogArea {
            name: c.to_string(),
            level: rtt::log::level(c).map_err(not_found)?,
        }],
        None => rtt::log::levels()
            .into_iter()
            .map(|(name, level)| crate::protocol::LogArea { name, level })
            .collect(),
    };
    to_value(crate::protocol::LogLevels {
        areas,
        counters: rtt::log::stats(),
    })
}

/// Runs a lifecycle command; the answer is the new state.
fn lifecycle(
    t: rtt::TaskContext,
    f: impl FnOnce(&rtt::TaskContext) -> Result<(), rtt::component::LifecycleError>,
) -> Result<Value, Fail> {
    f(&t).map_err(failed)?;
    to_value(t.state())
}

/// A run-time change of the deployment ([`crate::changes`]), or what it lists.
fn change(gw: &Gateway, req: &Request) -> Result<Value, Fail> {
    use crate::changes::{Change, ChangeError, table};
    let fail = |e: ChangeError| match e {
        ChangeError::NoComponent { .. } | ChangeError::NoConnection { .. } => not_found(e),
        ChangeError::Invalid(_) | ChangeError::BadName(_) => {
            Fail(ErrorKind::BadRequest, e.to_string())
        }
        _ => failed(e),
    };
    let report = match req {
        Request::Load { component } => {
            let t = table(component, "component").map_err(fail)?;
            gw.change(Change::Load(t))
        }
        Request::Unload { component } => gw.change(Change::Unload(component.clone())),
        Request::Connect { from, to, policy } => {
            let policy = match policy {
                Some(p) => Some(toml::Value::Table(table(p, "policy").map_err(fail)?)),
                None => None,
            };
            let changed = gw
                .change(Change::Connect {
                    from: from.clone(),
                    to: to.clone(),
                    policy,
                })
                .map_err(fail)?;
            return Ok(serde_json::json!({
                "id": changed.id,
                "applied": changed.report.applied,
            }));
        }
        Request::Disconnect { connection } => gw.change(Change::Disconnect(*connection)),
        Request::SetPeriod {
            component,
            period_ms,
        } => {
            let change = crate::changes::ActivityChange::Period(*period_ms);
            return gw
                .set_activity(component, change)
                .map_err(fail)
                .map(|()| Value::Null);
        }
        Request::SetPriority {
            component,
            policy,
            priority,
        } => {
            let change = crate::changes::ActivityChange::Thread(*policy, *priority);
            return gw
                .set_activity(component, change)
                .map_err(fail)
                .map(|()| Value::Null);
        }
        Request::Changes => return to_value(gw.changes()),
        _ => return to_value(gw.deployment_text()),
    };
    report.map_err(fail).and_then(|c| to_value(c.report))
}

/// A component's properties, attributes and constants, read and set.
fn values(t: &rtt::TaskContext, req: &Request) -> Result<Value, Fail> {
    let set = |bag: &rtt::property::PropertyBag, path: &str, value: &Value| {
        bag.set_value(path, value.clone())
            .map_err(failed)
            .map(|()| Value::Null)
    };
    match req {
        Request::Get {
            target: Target::Property(p),
            ..
        } => t.properties().get_value(p).map_err(not_found),
        Request::Get {
            target: Target::Attribute(a),
            ..
        } => t.attributes().get_value(a).map_err(not_found),
        Request::Set {
            target: Target::Property(p),
            value,
            ..
        } => set(t.properties(), p, value),
        Request::Set {
            target: Target::Attribute(a),
            value,
            ..
        } => set(t.attributes(), a, value),
        Request::LoadProperties { properties, .. } => {
            let table = crate::changes::table(properties, "properties")
                .map_err(|e| Fail(ErrorKind::BadRequest, e.to_string()))?;
            t.properties()
                .load_toml(&table)
                .map_err(failed)
                .map(|()| Value::Null)
        }
        _ => toml::to_string(&t.properties().to_toml())
            .map_err(failed)
            .and_then(to_value),
    }
}
