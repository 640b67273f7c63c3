//! A deadline left to the thread's wait (`epoll_pwait2`) when the process turns over to
//! timers — as it does when any activity's thread finds the call refused — is armed on
//! the timer at its thread's next wait, not lost (its own process: the switch is global).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use rtt::activity::ActivitySpec;
use rtt::time::{Clock, MonotonicClock};
use rtt::{Component, Context, HookResult, Runtime, RuntimeOptions};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::wait_until as wait_for;

/// Per step: when, and whether its deadline passed.
type StepLog = Arc<Mutex<Vec<(Instant, bool)>>>;

/// Asks, at its first step only, for a step `gap` later.
struct AskOnce {
    gap: Duration,
    asked: bool,
    steps: StepLog,
}

impl Component for AskOnce {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let deadline = ctx.fd_events().deadline_passed();
        self.steps.lock().unwrap().push((Instant::now(), deadline));
        if !self.asked {
            self.asked = true;
            ctx.activity()
                .wake_at(MonotonicClock.now().saturating_add(self.gap))?;
        }
        Ok(())
    }
}

#[test]
fn a_deadline_waiting_when_the_process_turns_to_timers_still_comes() {
    // The test's threads are SCHED_OTHER: they wait as a real-time one would, at first.
    rtt::activity::use_precise_deadlines_for_every_thread();
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let steps = StepLog::default();
    let s = steps.clone();
    let gap = Duration::from_millis(300);
    let t = rt
        .add(
            "once",
            ActivitySpec::file_descriptor(None),
            rtt::InitialState::Stopped,
            move |_| {
                Ok(AskOnce {
                    gap,
                    asked: false,
                    steps: s,
                })
            },
        )
        .unwrap();
    t.start().unwrap();
    let asked = Instant::now();
    t.trigger();
    wait_for("the step that asks", || !steps.lock().unwrap().is_empty());
    // Stopped with the deadline left to the wait; the process turns to timers meanwhile.
    t.stop().unwrap();
    rtt::activity::use_timer_deadlines();
    t.start().unwrap();
    wait_for("the deadline step after the restart", || {
        steps.lock().unwrap().iter().any(|(_, d)| *d)
    });
    t.stop().unwrap();
    let steps = steps.lock().unwrap();
    let (at, _) = steps.iter().find(|(_, d)| *d).unwrap();
    assert!(
        at.duration_since(asked) >= gap,
        "the deadline step came {:?} after the request, not before {gap:?}",
        at.duration_since(asked)
    );
}
