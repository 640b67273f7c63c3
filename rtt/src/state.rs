//! The lifecycle states of RTT 2.x, and the atomic cell a component keeps its state in.

use serde::Serialize;
use std::fmt;
use std::sync::atomic::{AtomicU8, Ordering};

/// The lifecycle states of RTT 2.x.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskState {
    /// Being built.
    Init,
    /// Built; needs `configure`.
    PreOperational,
    /// Configured; not stepping.
    Stopped,
    /// Stepping: `update` runs at each step.
    Running,
    /// Stepping, but `error` runs instead of `update` until `recover`.
    RunTimeError,
    /// A hook failed or panicked; the component stopped. `recover` brings it to Stopped.
    Exception,
    /// Handling an exception failed too; nothing more will run.
    FatalError,
}

impl TaskState {
    const ALL: [TaskState; 7] = [
        TaskState::Init,
        TaskState::PreOperational,
        TaskState::Stopped,
        TaskState::Running,
        TaskState::RunTimeError,
        TaskState::Exception,
        TaskState::FatalError,
    ];

    fn from_u8(v: u8) -> TaskState {
        Self::ALL
            .get(usize::from(v))
            .copied()
            .unwrap_or(TaskState::FatalError)
    }

    fn as_u8(self) -> u8 {
        Self::ALL.iter().position(|s| *s == self).unwrap_or(6) as u8
    }
}

impl fmt::Display for TaskState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
}

/// A [`TaskState`] readable from any thread without a lock.
#[derive(Debug)]
pub(crate) struct StateCell(AtomicU8);

impl StateCell {
    pub(crate) fn new(state: TaskState) -> Self {
        StateCell(AtomicU8::new(state.as_u8()))
    }

    pub(crate) fn get(&self) -> TaskState {
        TaskState::from_u8(self.0.load(Ordering::Acquire))
    }

    pub(crate) fn set(&self, state: TaskState) {
        self.0.store(state.as_u8(), Ordering::Release);
    }
}

/// The state a component is in once built: [`Stopped`](TaskState::Stopped), ready to
/// start, or [`PreOperational`](TaskState::PreOperational) when it must be configured
/// first (RTT 2.x's `TaskContext(name, initial_state)`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum InitialState {
    /// Ready to start.
    #[default]
    Stopped,
    /// Needs `configure` before it can start.
    PreOperational,
}

impl From<InitialState> for TaskState {
    fn from(s: InitialState) -> TaskState {
        match s {
            InitialState::Stopped => TaskState::Stopped,
            InitialState::PreOperational => TaskState::PreOperational,
        }
    }
}
