//! Required services bound to a component of another gateway on Zenoh:
//! `requires = { limit = "B/thr.limit" }` (the remote providers, RTT 2.0 road map
//! L74–76: lost and back like a local provider).
//!
//! The binding's operations are calls through the control requests that already reach
//! other gateways ([`crate::forward`]): `call` with the arguments as JSON, the answer
//! converted to the required result type. A watcher thread asks the provider's gateway
//! for the component every [`POLL`] (`describe`): the binding is ready while that
//! gateway answers, the component is Running and each required operation is there with
//! the required type; otherwise it is not ready, and the requiring component is told
//! (`service_lost`) and counted as for a local provider. A call that gets no answer makes
//! it not ready at once; the watcher's own look may wait for the Zenoh request timeout
//! (`request_timeout_ms`, 2 s by default), so a gateway gone silent is seen within a poll
//! and that timeout. A mismatch of types is logged once, naming the operation and both
//! types. The watcher ends when the binding goes (the component unloaded, rebuilt, bound
//! elsewhere). A remote call waits for the other gateway's answer, up to that timeout:
//! make one from a component that may wait, never on a real-time path.
//!
//! `hwgw check` cannot see the other gateway: it checks the address's form only.

/// How often the provider's gateway is asked for the component.
pub const POLL: std::time::Duration = std::time::Duration::from_millis(200);

#[cfg(feature = "zenoh")]
pub(crate) use imp::bind;

/// A build without Zenoh binds no service of another gateway.
#[cfg(not(feature = "zenoh"))]
pub(crate) fn bind(
    _node: Option<&std::sync::Arc<crate::remote::Node>>,
    _task: &rtt::TaskContext,
    _requirement: &str,
    address: &str,
) -> Result<(), String> {
    Err(format!(
        "{address:?} is a service of another gateway, and this build has no Zenoh"
    ))
}

#[cfg(feature = "zenoh")]
mod imp {
    use super::POLL;
    use crate::remote::Node;
    use device_interface::text::Cut;
    use rtt::service::{RemoteCall, RemoteProvider, RemoteState, RequiredKind};
    use rtt::{TaskContext, TaskState};
    use serde_json::{Value, json};
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    /// `(gateway, component, service)` of `gateway/component.service`.
    fn split(address: &str) -> Result<(&str, &str, &str), String> {
        let bad = || {
            format!("{address:?}: a service of another gateway is \"gateway/component.service\"")
        };
        let (gw, rest) = address.split_once('/').ok_or_else(bad)?;
        let (component, service) = rest.rsplit_once('.').ok_or_else(bad)?;
        if !scaleout::config::is_gateway_name(gw) {
            return Err(format!(
                "{address:?}: {gw:?} cannot name a gateway (1 to 64 letters, digits, '_' or '-')"
            ));
        }
        if component.is_empty() || service.is_empty() {
            return Err(bad());
        }
        Ok((gw, component, service))
    }

    /// Binds `task`'s requirement `requirement` to `address`
    /// (`gateway/component.service`) through `node`.
    pub(crate) fn bind(
        node: Option<&Arc<Node>>,
        task: &TaskContext,
        requirement: &str,
        address: &str,
    ) -> Result<(), String> {
        let (gw, component, service) = split(address)?;
        let Some(node) = node else {
            return Err(format!(
                "{address:?} is a service of gateway {gw:?}, but this one has no [zenoh] section"
            ));
        };
        if gw == node.name() {
            return Err(format!(
                "{address:?}: {gw:?} is this gateway; bind \"{component}.{service}\""
            ));
        }
        let (required, bound_to) = task
            .required()
            .into_iter()
            .find(|r| r.name == requirement)
            .map(|r| match r.kind {
                RequiredKind::Service { operations } => (operations, r.bound_to),
                RequiredKind::Devices { .. } => (Vec::new(), r.bound_to),
            })
            .unwrap_or_default();
        if bound_to.first().map(String::as_str) == Some(address) {
            // Bound there already: its watcher runs on.
            return Ok(());
        }
        let stop = Arc::new(AtomicBool::new(false));
        let state = RemoteState::default();
        let call = Arc::new(ZenohCall {
            node: node.clone(),
            gateway: gw.to_string(),
            component: component.to_string(),
            stop: stop.clone(),
            state: state.clone(),
        });
        let provider = RemoteProvider {
            label: address.to_string(),
            service: service.to_string(),
            state: state.clone(),
            call,
        };
        // The watcher first: a binding without one would never be ready. It ends with the
        // provider's caller, bound below or dropped at once when the binding is refused.
        let watch = Watch {
            node: node.clone(),
            label: format!("{}: {address}", task.name()),
            gateway: gw.to_string(),
            component: component.to_string(),
            service: service.to_string(),
            required,
            state,
            stop,
        };
        std::thread::Builder::new()
            .name(format!("svc {address}"))
            .spawn(move || watch.run())
            .map_err(|e| format!("{address:?}: no thread to watch it: {e}"))?;
        task.bind_remote_service(requirement, &provider, false)
            .map_err(|e| e.to_string())
    }

    /// Calls through the provider's gateway; dropped with the binding, it ends its watcher.
    struct ZenohCall {
        node: Arc<Node>,
        gateway: String,
        component: String,
        stop: Arc<AtomicBool>,
        /// Set not Running when a call gets no answer (the watcher sets it again).
        state: RemoteState,
    }

    impl Drop for ZenohCall {
        fn drop(&mut self) {
            self.stop.store(true, Ordering::Release);
        }
    }

    impl RemoteCall for ZenohCall {
        fn call(&self, operation: &str, args: Vec<Value>) -> Result<Value, String> {
            let req = json!({
                "cmd": "call",
                "component": self.component,
                "operation": operation,
                "args": args,
            });
            let reply = self.node.request(&self.gateway, &req).map_err(|e| {
                // No answer: not ready from now until the watcher hears the provider again.
                self.state.set(TaskState::Stopped);
                e.to_string()
            })?;
            crate::protocol::reply_body(reply)
                .map_err(|(_, m)| format!("{}: {}", self.gateway, Cut(&m)))
        }
    }

    /// Why a look heard no usable provider.
    enum Heard {
        /// This gateway's node is not started (yet, or ever: a check's build).
        NotStarted,
        /// Why not.
        Not(String),
    }

    impl std::fmt::Display for Heard {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            match self {
                Heard::NotStarted => f.write_str("this gateway's Zenoh node is not started"),
                Heard::Not(why) => f.write_str(why),
            }
        }
    }

    /// What a watcher knows.
    struct Watch {
        node: Arc<Node>,
        /// `requirer: address`, for the log.
        label: String,
        gateway: String,
        component: String,
        service: String,
        /// The required operations, `name(types) -> result`.
        required: Vec<String>,
        state: RemoteState,
        stop: Arc<AtomicBool>,
    }

    impl Watch {
        fn run(self) {
            let mut last: Option<Result<TaskState, String>> = None;
            while !self.stop.load(Ordering::Acquire) {
                let heard = self.look();
                let state = heard.as_ref().copied().unwrap_or(TaskState::Stopped);
                self.state.set(state);
                // The node not started yet (or a check's build): nothing to tell.
                let quiet = matches!(&heard, Err(Heard::NotStarted));
                let heard = heard.map_err(|h| h.to_string());
                if !quiet && last.as_ref() != Some(&heard) {
                    match &heard {
                        Ok(s) => tracing::info!("{}: the provider is {s}", self.label),
                        Err(why) => tracing::warn!("{}: not ready: {why}", self.label),
                    }
                    last = Some(heard);
                }
                // In short naps, so a binding that goes ends its watcher soon.
                let until = std::time::Instant::now() + POLL;
                while std::time::Instant::now() < until && !self.stop.load(Ordering::Acquire) {
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
            }
            self.state.set(TaskState::Stopped);
        }

        /// The provider's state, its operations' types checked; or why it cannot be used.
        fn look(&self) -> Result<TaskState, Heard> {
            let req = json!({"cmd": "describe", "component": self.component});
            let reply = match self.node.request(&self.gateway, &req) {
                Ok(r) => r,
                Err(scaleout::NodeError::NotStarted) => return Err(Heard::NotStarted),
                Err(e) => return Err(Heard::Not(e.to_string())),
            };
            let d = crate::protocol::reply_body(reply)
                .map_err(|(_, m)| Heard::Not(format!("{}: {}", self.gateway, Cut(&m))))?;
            let offered: Vec<rtt::operation::OperationInfo> = d["operations"]
                .as_array()
                .map(Vec::as_slice)
                .unwrap_or_default()
                .iter()
                .filter_map(|o| serde_json::from_value(o.clone()).ok())
                .collect();
            let at = format!("{}/{}", self.gateway, self.component);
            check_types(&at, &self.service, &self.required, &offered).map_err(Heard::Not)?;
            serde_json::from_value(d["state"].clone()).map_err(|e| {
                Heard::Not(format!(
                    "{}/{}: no state in its description: {e}",
                    self.gateway, self.component
                ))
            })
        }
    }

    /// Checks that `offered` (the operations of component `at`) has every `required`
    /// operation of `service` (`name(types) -> result`), of the same type.
    fn check_types(
        at: &str,
        service: &str,
        required: &[String],
        offered: &[rtt::operation::OperationInfo],
    ) -> Result<(), String> {
        let prefix = format!("{service}.");
        let offered: Vec<String> = offered
            .iter()
            .filter_map(|o| {
                let member = o.name.strip_prefix(&prefix)?;
                Some(format!("{member}{}", rtt::service::info_signature(o)))
            })
            .collect();
        if offered.is_empty() {
            return Err(format!("{at} provides no service {service:?}"));
        }
        match required.iter().find(|r| !offered.contains(r)) {
            Some(missing) => Err(format!(
                "it requires {service}.{missing}; {at} offers {}",
                offered.join(", ")
            )),
            None => Ok(()),
        }
    }

    #[cfg(test)]
    mod tests {
        use super::{check_types, split};
        use rtt::operation::{ArgInfo, ExecutionThread, OperationInfo};

        fn op(name: &str, args: &[&str], result: &str) -> OperationInfo {
            OperationInfo {
                name: name.into(),
                doc: String::new(),
                args: args
                    .iter()
                    .map(|t| ArgInfo {
                        name: "x".into(),
                        doc: String::new(),
                        type_name: (*t).into(),
                    })
                    .collect(),
                result: result.into(),
                thread: ExecutionThread::ClientThread,
            }
        }

        #[test]
        fn the_remote_operations_types_are_checked() {
            let required = ["set(f64)".to_string(), "is_on() -> bool".to_string()];
            let good = [
                op("limit.set", &["f64"], ""),
                op("limit.is_on", &[], "bool"),
            ];
            assert_eq!(check_types("B/thr", "limit", &required, &good), Ok(()));
            let other = [
                op("limit.set", &["u32"], ""),
                op("limit.is_on", &[], "bool"),
            ];
            assert_eq!(
                check_types("B/thr", "limit", &required, &other),
                Err("it requires limit.set(f64); B/thr offers set(u32), is_on() -> bool".into())
            );
            assert_eq!(
                check_types("B/thr", "limit", &required, &[op("is_on", &[], "bool")]),
                Err("B/thr provides no service \"limit\"".into())
            );
        }

        #[test]
        fn an_address_names_gateway_component_and_service() {
            assert_eq!(split("B/cam0.camera"), Ok(("B", "cam0", "camera")));
            assert_eq!(split("B/sim0.ai.limit"), Ok(("B", "sim0.ai", "limit")));
            assert!(split("B/cam0").is_err());
            assert!(
                split("*/cam0.camera")
                    .unwrap_err()
                    .contains("cannot name a gateway")
            );
            assert!(split("B/.camera").is_err());
        }
    }
}
