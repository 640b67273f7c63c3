//! Services provided in another process — a component of another gateway, reached over
//! Zenoh — bound to a component's requirement as a local provider's are (RTT 2.0 road
//! map L74–76: a remote provider is lost and back like a local one).
//!
//! Whoever reaches the other process (the gateway, with its Zenoh node) gives a
//! [`RemoteProvider`]: a label (`B/cam0.camera`), the service's name there, a
//! [`RemoteState`] it keeps current (the remote component's state as last heard; not
//! Running while it is not heard from or its types do not match), and a [`RemoteCall`]
//! that carries one call's arguments and result as JSON.
//! [`TaskContext::bind_remote_service`](crate::TaskContext::bind_remote_service) binds a
//! requirement's operations to it. Readiness stays a lock-free look; a call waits for the
//! other process's answer (at most its own timeout), so it is not for a real-time path.

use crate::operation::{CallError, Invoke, SendHandle};
use crate::state::{StateCell, TaskState};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::marker::PhantomData;
use std::sync::Arc;

/// Carries out calls of a remote provider's operations.
pub trait RemoteCall: Send + Sync {
    /// Calls `operation` (`service.member`) with `args`; waits for the answer, a JSON
    /// value, or says why there is none.
    fn call(
        &self,
        operation: &str,
        args: Vec<serde_json::Value>,
    ) -> Result<serde_json::Value, String>;
}

/// A remote provider's state as its owner last heard it: what the requirement's
/// readiness reads.
#[derive(Clone)]
pub struct RemoteState(pub(crate) Arc<StateCell>);

impl Default for RemoteState {
    fn default() -> Self {
        RemoteState(Arc::new(StateCell::new(TaskState::Stopped)))
    }
}

impl RemoteState {
    /// Sets the state heard (Running makes the binding ready).
    pub fn set(&self, state: TaskState) {
        self.0.set(state);
    }

    /// The state last set.
    pub fn get(&self) -> TaskState {
        self.0.get()
    }
}

/// A service of another process, as a requirement binds it.
#[derive(Clone)]
pub struct RemoteProvider {
    /// How listings show the binding (`B/cam0.camera`).
    pub label: String,
    /// The service's name at the provider (`camera`).
    pub service: String,
    /// Kept current by the owner.
    pub state: RemoteState,
    /// Carries the calls; held while the binding lasts (an owner that watches the remote
    /// side may stop when it is dropped).
    pub call: Arc<dyn RemoteCall>,
}

/// `answer` as an `R`. The type names the protocol compares show a `Result<T, E>` as its
/// `T`, so either side may have a `Result` the other has not: `{"Ok": v}` is taken as `v`,
/// `{"Err": e}` as the error `e`, and a plain `v` as `{"Ok": v}`.
fn result_of<R: DeserializeOwned>(answer: &serde_json::Value) -> Result<R, String> {
    let direct = R::deserialize(answer).map_err(|e| e.to_string());
    if direct.is_ok() {
        return direct;
    }
    if let Some(o) = answer.as_object().filter(|o| o.len() == 1) {
        if let Some(v) = o.get("Ok") {
            return R::deserialize(v).map_err(|e| e.to_string());
        }
        if let Some(e) = o.get("Err") {
            let text = e.as_str().map_or_else(|| e.to_string(), str::to_string);
            return Err(format!(
                "the provider answered an error: {}",
                device_interface::text::Cut(&text)
            ));
        }
    }
    R::deserialize(serde_json::json!({ "Ok": answer }))
        .map_err(|_| direct.err().unwrap_or_default())
}

/// A required operation bound to a remote provider's operation `name`.
pub(crate) struct RemoteOp<A, R> {
    pub(crate) name: Arc<str>,
    pub(crate) call: Arc<dyn RemoteCall>,
    pub(crate) _types: PhantomData<fn(A) -> R>,
}

impl<A, R> Invoke<A, R> for RemoteOp<A, R>
where
    A: Serialize + Send + 'static,
    R: DeserializeOwned + Send + 'static,
{
    fn call(&self, args: A) -> Result<R, CallError> {
        let remote = |message: String| CallError::Remote {
            operation: self.name.to_string(),
            message,
        };
        let args = match serde_json::to_value(&args).map_err(|e| remote(e.to_string()))? {
            serde_json::Value::Null => Vec::new(),
            serde_json::Value::Array(a) => a,
            one => vec![one],
        };
        let answer = self.call.call(&self.name, args).map_err(remote)?;
        result_of(&answer).map_err(|e| {
            if e.starts_with("the provider answered an error") {
                return remote(e);
            }
            remote(format!(
                "the answer {} is not of the type required: {e}",
                device_interface::text::Cut(&answer.to_string())
            ))
        })
    }

    /// Waits for the answer as [`call`](Self::call) does: the call is in another process.
    fn send(&self, args: A) -> SendHandle<R> {
        SendHandle::ready(Invoke::call(self, args))
    }
}

#[cfg(test)]
mod tests {
    use super::result_of;
    use serde_json::json;

    #[test]
    fn a_result_on_either_side_is_taken_as_its_value() {
        assert_eq!(result_of::<bool>(&json!(true)), Ok(true));
        assert_eq!(result_of::<bool>(&json!({"Ok": true})), Ok(true));
        assert_eq!(
            result_of::<Result<bool, String>>(&json!(true)),
            Ok(Ok(true))
        );
        assert_eq!(
            result_of::<Result<bool, String>>(&json!({"Err": "no"})),
            Ok(Err("no".to_string()))
        );
        assert_eq!(
            result_of::<()>(&json!({"Err": "the valve is stuck"})),
            Err("the provider answered an error: the valve is stuck".to_string())
        );
        assert!(result_of::<u32>(&json!("x")).is_err());
    }
}
