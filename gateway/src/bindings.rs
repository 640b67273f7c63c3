//! Binding the deployment's required services and devices (a `[[component]]`'s
//! `requires`), the RTT 2.0 road map's "connect provided to required services" (L458–464,
//! L614–628): each named binding resolved and type-checked, a required service not named
//! bound to the one component providing a service of its name, every problem located at
//! its key. Components then start providers first, so a requirer's first step sees its
//! services ready.

use crate::config::{Binding, ComponentConfig};
use crate::problems::{KeyPath, Problems};
use rtt::service::{RequiredInfo, RequiredKind};
use rtt::{Runtime, TaskContext};

/// `component.service` of `address` among the runtime's components: the split whose
/// component exists and provides the service (component names may hold dots: `sim0.ai`).
fn provider(runtime: &Runtime, address: &str) -> Result<(TaskContext, String), String> {
    for (i, _) in address.match_indices('.') {
        let (component, service) = (&address[..i], &address[i + 1..]);
        if let Ok(t) = runtime.component(component)
            && t.provided().iter().any(|p| p.name == service)
        {
            return Ok((t, service.to_string()));
        }
    }
    let offers: Vec<String> = runtime
        .components()
        .iter()
        .flat_map(|t| {
            t.provided()
                .into_iter()
                .map(|p| format!("{}.{}", t.name(), p.name))
                .collect::<Vec<_>>()
        })
        .collect();
    Err(format!(
        "no component provides {address:?}; provided here: {}",
        if offers.is_empty() {
            "none".to_string()
        } else {
            offers.join(", ")
        }
    ))
}

/// The components other than `task` that provide service `service`.
fn providers_of(runtime: &Runtime, task: &TaskContext, service: &str) -> Vec<TaskContext> {
    runtime
        .components()
        .into_iter()
        .filter(|t| t.name() != task.name() && t.provided().iter().any(|p| p.name == service))
        .collect()
}

/// Binds `task`'s requirements as `c` says, and the services it does not name
/// automatically; each problem at `at` (the component's path). A service of another
/// gateway (`B/cam0.camera`) is bound through `zenoh` ([`crate::remote_services`]). True
/// when all went well.
pub(crate) fn bind(
    runtime: &Runtime,
    task: &TaskContext,
    (c, at): (&ComponentConfig, &KeyPath),
    zenoh: Option<&std::sync::Arc<crate::remote::Node>>,
    problems: &mut Problems,
) -> bool {
    let mut ok = true;
    let mut fail = |path: &KeyPath, msg: String| {
        problems.at(path, msg);
        ok = false;
    };
    let required = task.required();
    for (name, binding) in &c.requires {
        let key = at.key("requires").key(name);
        let Some(req) = required.iter().find(|r| &r.name == name) else {
            let known: Vec<&str> = required.iter().map(|r| r.name.as_str()).collect();
            fail(
                &key,
                format!(
                    "{:?} (type {:?}) requires no {name:?}; it requires: {}",
                    c.name,
                    c.kind,
                    if known.is_empty() {
                        "nothing".to_string()
                    } else {
                        known.join(", ")
                    }
                ),
            );
            continue;
        };
        let result = match (&req.kind, binding) {
            (RequiredKind::Service { .. }, Binding::One(address)) if address.contains('/') => {
                crate::remote_services::bind(zenoh, task, name, address)
            }
            (RequiredKind::Service { .. }, Binding::One(address)) => provider(runtime, address)
                .and_then(|(p, service)| {
                    task.bind_service(name, &p, &service, false)
                        .map_err(|e| e.to_string())
                }),
            (RequiredKind::Service { .. }, Binding::Many(_)) => Err(format!(
                "{name:?} is a service: bind it to one \"component.service\""
            )),
            (RequiredKind::Devices { .. }, Binding::One(device)) => task
                .bind_devices(name, std::slice::from_ref(device), false)
                .map_err(|e| e.to_string()),
            (RequiredKind::Devices { .. }, Binding::Many(devices)) => task
                .bind_devices(name, devices, false)
                .map_err(|e| e.to_string()),
        };
        if let Err(msg) = result {
            fail(&key, msg);
        }
    }
    for req in required
        .iter()
        .filter(|r| !c.requires.contains_key(&r.name))
    {
        if let Err(msg) = bind_unnamed(runtime, task, req) {
            fail(at, msg);
        }
    }
    ok
}

/// A requirement the deployment does not name: a service bound to its one provider;
/// otherwise fine only when it is optional.
fn bind_unnamed(runtime: &Runtime, task: &TaskContext, req: &RequiredInfo) -> Result<(), String> {
    let name = &req.name;
    match &req.kind {
        RequiredKind::Service { .. } => {
            let found = providers_of(runtime, task, name);
            match found.as_slice() {
                [p] => task
                    .bind_service(name, p, name, false)
                    .map_err(|e| e.to_string()),
                // Bound before (a reload took its name away) and now to nothing: unbound,
                // so no provider it no longer names goes on serving it.
                [] if req.optional && !req.bound_to.is_empty() => {
                    task.unbind(name).map_err(|e| e.to_string())
                }
                [] if req.optional => Ok(()),
                [] => Err(format!(
                    "{:?} requires service {name:?}, which no component provides; bind it \
                     with requires = {{ {name} = \"component.service\" }}",
                    task.name()
                )),
                many => Err(format!(
                    "{:?} requires service {name:?}, which {} provide; say which with \
                     requires = {{ {name} = \"{}.{name}\" }}",
                    task.name(),
                    many.iter().map(|t| t.name()).collect::<Vec<_>>().join(", "),
                    many[0].name()
                )),
            }
        }
        RequiredKind::Devices { .. } if req.optional => Ok(()),
        RequiredKind::Devices {
            interface,
            multiplicity,
        } => Err(format!(
            "{:?} requires {multiplicity} {interface} devices as {name:?}; name them with \
             requires = {{ {name} = [\"device\", …] }}",
            task.name()
        )),
    }
}

/// `bound` reordered so each component starts after the components whose services it is
/// bound to: a topological order, stable (the written order among the rest); a cycle is
/// started in its written order.
pub(crate) fn providers_first(bound: Vec<(TaskContext, bool)>) -> Vec<(TaskContext, bool)> {
    let names: Vec<String> = bound.iter().map(|(t, _)| t.name().to_string()).collect();
    // The provider among `bound` of binding `label` (`provider.service`): the longest name
    // it starts with (names may hold dots).
    let provider = |label: &str| {
        names
            .iter()
            .enumerate()
            .filter(|(_, n)| {
                label
                    .strip_prefix(n.as_str())
                    .is_some_and(|rest| rest.starts_with('.'))
            })
            .max_by_key(|(_, n)| n.len())
            .map(|(j, _)| j)
    };
    let needs: Vec<Vec<usize>> = bound
        .iter()
        .enumerate()
        .map(|(i, (t, _))| {
            t.required()
                .iter()
                .filter(|r| matches!(r.kind, RequiredKind::Service { .. }))
                .filter_map(|r| r.bound_to.first().and_then(|l| provider(l)))
                .filter(|&j| j != i)
                .collect()
        })
        .collect();
    let mut placed = vec![false; bound.len()];
    let mut order = Vec::with_capacity(bound.len());
    while order.len() < bound.len() {
        let next = (0..bound.len())
            .find(|&i| !placed[i] && needs[i].iter().all(|&j| placed[j]))
            // A cycle: the first left, in the written order.
            .or_else(|| (0..bound.len()).find(|&i| !placed[i]));
        let Some(i) = next else { break };
        placed[i] = true;
        order.push(i);
    }
    let mut slots: Vec<Option<(TaskContext, bool)>> = bound.into_iter().map(Some).collect();
    order.into_iter().filter_map(|i| slots[i].take()).collect()
}

#[cfg(test)]
mod tests {
    use super::providers_first;
    use rtt::{ActivitySpec, Component, InitialState, Runtime, RuntimeOptions};
    use std::sync::Arc;

    struct Nothing;
    impl Component for Nothing {}

    /// A chain D needs C needs B needs A, written backwards, starts A, B, C, D.
    #[test]
    fn a_chain_starts_providers_first() {
        let rt = Runtime::new(Arc::default(), RuntimeOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        let add = |name: &str, needs: Option<&str>| {
            let needs = needs.map(str::to_string);
            rt.add(
                name,
                ActivitySpec::Slave,
                InitialState::Stopped,
                move |iface| {
                    iface
                        .provides("s")
                        .client_operation("f", "", &[], |(): ()| 1u8)?;
                    if needs.is_some() {
                        let _ = iface.requires("up").operation::<(), u8>("f")?;
                    }
                    Ok(Nothing)
                },
            )
            .unwrap_or_else(|e| panic!("{e}"))
        };
        let (d, c, b, a) = (
            add("d", Some("c")),
            add("c", Some("b")),
            add("b", Some("a")),
            add("a", None),
        );
        for (t, p) in [(&d, &c), (&c, &b), (&b, &a)] {
            t.bind_service("up", p, "s", false)
                .unwrap_or_else(|e| panic!("{e}"));
        }
        let order: Vec<String> = providers_first(vec![(d, true), (c, true), (b, true), (a, true)])
            .into_iter()
            .map(|(t, _)| t.name().to_string())
            .collect();
        assert_eq!(order, ["a", "b", "c", "d"]);
    }
}
