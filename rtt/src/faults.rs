//! One policy for device faults, shared by the IO components, `blinker` and users'
//! components (manual L832–884: a warning keeps the component running, a RunTimeError
//! keeps it stepping its error hook until it recovers): consecutive missed readings — a
//! device stale or offline — raise the warning after `warn_after` and go to RunTimeError
//! after `error_after`; one good reading clears both. Corrupt data is no missed reading:
//! it is the component's to raise as an exception ([`Context::exception`]).

use crate::Context;
use serde::{Deserialize, Serialize};

/// When missed readings become a warning and an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultPolicy {
    /// Consecutive missed readings that raise the warning (0: never).
    #[serde(default = "default_warn")]
    pub warn_after: u32,
    /// Consecutive missed readings that go to RunTimeError (0: never).
    #[serde(default = "default_error")]
    pub error_after: u32,
}

fn default_warn() -> u32 {
    1
}

fn default_error() -> u32 {
    5
}

impl Default for FaultPolicy {
    /// One missed reading warns, five in a row are an error (the manual's socket device).
    fn default() -> Self {
        FaultPolicy {
            warn_after: default_warn(),
            error_after: default_error(),
        }
    }
}

impl FaultPolicy {
    /// Never warns nor errs: missed readings are only the device's health to tell.
    pub const NEVER: FaultPolicy = FaultPolicy {
        warn_after: 0,
        error_after: 0,
    };

    /// Why the policy makes no sense, if it does not: an error before the warning.
    pub fn check(&self) -> Result<(), FaultPolicyError> {
        if self.warn_after > 0 && self.error_after > 0 && self.error_after < self.warn_after {
            return Err(FaultPolicyError {
                warn_after: self.warn_after,
                error_after: self.error_after,
            });
        }
        Ok(())
    }
}

/// A policy whose error comes before its warning.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "error_after ({error_after}) comes before warn_after ({warn_after}): the error must follow the warning"
)]
pub struct FaultPolicyError {
    /// The policy's warn_after.
    pub warn_after: u32,
    /// The policy's error_after.
    pub error_after: u32,
}

/// Counts a component's consecutive missed readings against its [`FaultPolicy`]. No
/// allocation, no lock: for `update_hook` and `error_hook`.
#[derive(Debug, Clone, Copy, Default)]
pub struct FaultCounter {
    policy: FaultPolicy,
    run: u32,
}

impl FaultCounter {
    /// A counter under `policy`, nothing missed yet.
    pub fn new(policy: FaultPolicy) -> Self {
        FaultCounter { policy, run: 0 }
    }

    /// A reading was missed (the device stale or offline): the warning at `warn_after`,
    /// RunTimeError at `error_after` in a row.
    pub fn missed(&mut self, ctx: &mut Context<'_>) {
        self.run = self.run.saturating_add(1);
        let p = self.policy;
        if p.error_after > 0 && self.run >= p.error_after {
            ctx.error();
        } else if p.warn_after > 0 && self.run >= p.warn_after {
            ctx.warning();
        }
    }

    /// A good reading: the count starts again; the warning is cleared and a component in
    /// RunTimeError returns to Running (whoever put it there: the operator's `error` too).
    pub fn good(&mut self, ctx: &mut Context<'_>) {
        if self.run > 0 || ctx.state() == crate::TaskState::RunTimeError {
            self.run = 0;
            ctx.recovered();
        }
    }

    /// Missed readings in a row now.
    pub fn run(&self) -> u32 {
        self.run
    }
}
