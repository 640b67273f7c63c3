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
    if address.contains('/') {
        return Err(format!(
            "{address:?}: a service of another gateway cannot be bound yet; bind a service of \
             this gateway"
        ));
    }
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
/// automatically; each problem at `at` (the component's path). True when all went well.
pub(crate) fn bind(
    runtime: &Runtime,
    task: &TaskContext,
    c: &ComponentConfig,
    at: &KeyPath,
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

/// After a reload rebuilt the components `rebuilt`: the others' bindings to them are made
/// again, to the new components (the old ones are gone). Problems are returned as lines.
pub(crate) fn rebind_dependents(runtime: &Runtime, rebuilt: &[String]) -> Vec<String> {
    let mut problems = Vec::new();
    for task in runtime.components() {
        if rebuilt.iter().any(|r| r == task.name()) {
            continue;
        }
        for req in task.required() {
            let Some(target) = req.bound_to.first() else {
                continue;
            };
            if !matches!(req.kind, RequiredKind::Service { .. }) {
                continue;
            }
            let Some((provider, service)) = rebuilt.iter().find_map(|r| {
                target
                    .strip_prefix(r.as_str())
                    .and_then(|s| s.strip_prefix('.'))
                    .map(|s| (r, s))
            }) else {
                continue;
            };
            let result = runtime
                .component(provider)
                .map_err(|e| e.to_string())
                .and_then(|p| {
                    task.bind_service(&req.name, &p, service, false)
                        .map_err(|e| e.to_string())
                });
            if let Err(e) = result {
                problems.push(format!("{}: {e}", task.name()));
            }
        }
    }
    problems
}

/// `bound` reordered so each component starts after the components whose services it is
/// bound to (the order kept otherwise; a cycle keeps its order).
pub(crate) fn providers_first(mut bound: Vec<(TaskContext, bool)>) -> Vec<(TaskContext, bool)> {
    let n = bound.len();
    for _ in 0..n {
        let mut moved = false;
        for i in 0..bound.len() {
            let needs: Vec<String> = bound[i]
                .0
                .required()
                .iter()
                .filter_map(|r| r.bound_to.first().cloned())
                .collect();
            let last_provider = bound.iter().rposition(|(t, _)| {
                needs.iter().any(|b| {
                    b.strip_prefix(t.name())
                        .is_some_and(|rest| rest.starts_with('.'))
                })
            });
            if let Some(j) = last_provider
                && j > i
            {
                let item = bound.remove(i);
                bound.insert(j, item);
                moved = true;
                break;
            }
        }
        if !moved {
            break;
        }
    }
    bound
}
