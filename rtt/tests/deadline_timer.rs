//! The deadline tests of `deadlines/` through a timer: every deadline armed on the
//! activity's timerfd, as on a kernel without `epoll_pwait2` or behind a filter that
//! refuses it (its own process, so the switch reaches no other test binary).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use rtt::{Runtime, RuntimeOptions};
use std::sync::Arc;

mod deadlines;

/// A runtime whose activities wait for their deadlines through a timer.
fn runtime() -> Runtime {
    rtt::activity::use_timer_deadlines();
    Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap()
}
