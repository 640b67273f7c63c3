//! The runtime's errors: building components, lifecycle commands, lookups by name.

use crate::activity::ActivityError;
use crate::info::Direction;
use crate::operation::CallError;
use crate::port::ConnectError;
use crate::property::PropertyError;
use crate::state::TaskState;
use device_interface::RegistryError;
use std::sync::Arc;

/// Why the runtime could not do what was asked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RuntimeError {
    /// ThreadScope is on but no DigitalOut is registered as "ThreadScope".
    #[error("ThreadScope is on, but {0}")]
    ThreadScope(#[source] RegistryError),
    /// The ThreadScope recording could not be made.
    #[error(transparent)]
    ThreadScopeVcd(#[from] crate::scope::vcd::VcdError),
    /// Two components with one name.
    #[error("a component named {0:?} already exists")]
    Duplicate(String),
    /// No component of that name.
    #[error("no component named {name:?}; there are: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NotFound {
        /// The name asked for.
        name: String,
        /// The components that exist.
        known: Vec<String>,
    },
    /// The component's activity could not be made.
    #[error("component {component:?}: {source}")]
    Activity {
        /// The component.
        component: String,
        /// Why.
        #[source]
        source: Arc<ActivityError>,
    },
    /// The component's constructor failed.
    #[error("component {component:?}: {source}")]
    Build {
        /// The component.
        component: String,
        /// Why.
        #[source]
        source: IntrospectError,
    },
}

/// Why a lifecycle command was refused.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum LifecycleError {
    /// A hook asked for Exception ([`Context::exception`](crate::Context::exception)).
    #[error("component {component:?}: {hook} raised an exception: {message}; now in {state}")]
    Exception {
        /// The component.
        component: String,
        /// The hook.
        hook: &'static str,
        /// Its reason.
        message: String,
        /// The state now (Exception, or FatalError).
        state: crate::TaskState,
    },
    /// A requirement that is not optional is not bound.
    #[error("component {component:?}: required {requirement:?} is not bound")]
    Unbound {
        /// The component.
        component: String,
        /// The requirement.
        requirement: String,
    },
    /// Asked from the thread that is inside one of the component's own hooks or steps
    /// (a script stopping its own component, two components stopping each other from
    /// their hooks): refused, where waiting would never end.
    #[error("component {component:?}: cannot {command} from within its own step or hook")]
    Reentrant {
        /// The component.
        component: String,
        /// The command.
        command: &'static str,
    },
    /// The command is not allowed in the current state.
    #[error("component {component:?}: cannot {command} in state {state}")]
    Illegal {
        /// The component.
        component: String,
        /// The command.
        command: &'static str,
        /// The state it is in.
        state: TaskState,
    },
    /// The hook returned an error; the state did not change.
    #[error("component {component:?}: {hook} failed: {message}")]
    HookFailed {
        /// The component.
        component: String,
        /// The hook.
        hook: &'static str,
        /// Its error.
        message: String,
    },
    /// The hook panicked; the component went to Exception (or FatalError).
    #[error("component {component:?}: {hook} panicked: {message}; now in {state}")]
    HookPanicked {
        /// The component.
        component: String,
        /// The hook.
        hook: &'static str,
        /// The panic message.
        message: String,
        /// The state it ended in.
        state: TaskState,
    },
    /// The activity could not start.
    #[error("component {component:?}: {source}")]
    Activity {
        /// The component.
        component: String,
        /// The activity error.
        #[source]
        source: Arc<ActivityError>,
    },
}

/// Why something was not found or did not fit in a component's interface.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum IntrospectError {
    /// No such port, operation or component.
    #[error("{component:?} has no {kind} {name:?}; it has: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NotFound {
        /// The component (or "runtime").
        component: String,
        /// "port", "operation", "component".
        kind: &'static str,
        /// The name asked for.
        name: String,
        /// The names that exist.
        known: Vec<String>,
    },
    /// A name used twice in one interface.
    #[error("{component:?} already has a {kind} named {name:?}")]
    Duplicate {
        /// The component.
        component: String,
        /// "port", "operation".
        kind: &'static str,
        /// The name.
        name: String,
    },
    /// A typed lookup with the wrong types.
    #[error("{what} is {actual}, not {asked}")]
    WrongType {
        /// What was looked up.
        what: String,
        /// Its actual type.
        actual: String,
        /// The type asked for.
        asked: String,
    },
    /// A dynamically typed value that does not fit.
    #[error("{what}: expected {expected}: {detail}")]
    BadValue {
        /// What was written.
        what: String,
        /// The expected type.
        expected: String,
        /// What was wrong.
        detail: String,
    },
    /// A value that fits the port's type but that the port refuses (a device output's
    /// range).
    #[error("{what}: {detail}")]
    Refused {
        /// What was written.
        what: String,
        /// Why it was refused.
        detail: String,
    },
    /// An operation on a port of the wrong direction.
    #[error("port {port:?} is an {actual} port; {what} needs an {needed} port")]
    Direction {
        /// The port.
        port: String,
        /// Its direction.
        actual: Direction,
        /// The direction needed.
        needed: Direction,
        /// What was attempted.
        what: &'static str,
    },
    /// Connecting failed.
    #[error(transparent)]
    Connect(#[from] ConnectError),
    /// A property could not be added, found or set.
    #[error(transparent)]
    Property(#[from] PropertyError),
}

/// Either a lookup or a call failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallOrIntrospect {
    /// The lookup failed.
    #[error(transparent)]
    Introspect(#[from] IntrospectError),
    /// The call failed.
    #[error(transparent)]
    Call(#[from] CallError),
}
