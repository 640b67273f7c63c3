//! Why a hook failed: a message, and whether the failure is only the gateway holding its
//! outputs while it stops.

use device_interface::DeviceError;
use std::fmt;

/// Why a hook failed: a message (any error converts into one).
///
/// A write refused because the outputs are held ([`DeviceError::Held`]: the gateway is
/// stopping and drives its safe values) is no failure of the component: an update that
/// returns it is skipped, logged at debug level, and the component stays Running until
/// the stop reaches it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HookError {
    message: String,
    held: bool,
}

impl fmt::Display for HookError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl<E: std::error::Error + 'static> From<E> for HookError {
    fn from(e: E) -> Self {
        let held = (&e as &dyn std::any::Any)
            .downcast_ref::<DeviceError>()
            .is_some_and(|d| matches!(d, DeviceError::Held { .. }));
        HookError {
            message: e.to_string(),
            held,
        }
    }
}

impl HookError {
    /// A hook error with `message`.
    pub fn new(message: impl Into<String>) -> Self {
        HookError {
            message: message.into(),
            held: false,
        }
    }

    /// The message.
    pub fn message(&self) -> &str {
        &self.message
    }

    /// True when it is a write refused because the outputs are held (the gateway is
    /// stopping), not a failure.
    pub fn is_held(&self) -> bool {
        self.held
    }
}

/// What a hook returns.
pub type HookResult = Result<(), HookError>;
