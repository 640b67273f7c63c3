//! The deadline tests (`Activity::wake_at`), run by `activities.rs` as the kernel gives
//! them (`epoll_pwait2`'s own timeout) and by `deadline_timer.rs` through a timer, as on a
//! kernel without the call: the including crate's `runtime()` says which.

use super::runtime;
use rtt::activity::ActivitySpec;
use rtt::{Component, Context, HookResult, Runtime};
use std::io::Write;
use std::os::fd::{AsFd, AsRawFd};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::wait_until as wait_for;

/// Steps only at the deadlines it sets itself: each deadline step asks for the next one
/// `gap` later.
struct Ticker {
    gap: Duration,
    steps: Arc<Mutex<Vec<(Instant, bool)>>>,
}

impl Component for Ticker {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        use rtt::time::{Clock, MonotonicClock};
        ctx.activity()
            .wake_at(MonotonicClock.now().saturating_add(self.gap))?;
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        use rtt::time::{Clock, MonotonicClock};
        let deadline = ctx.fd_events().deadline_passed();
        self.steps.lock().unwrap().push((Instant::now(), deadline));
        if deadline {
            ctx.activity()
                .wake_at(MonotonicClock.now().saturating_add(self.gap))?;
        }
        Ok(())
    }
}

#[test]
fn fd_activity_wakes_at_the_deadlines_its_component_sets() {
    let rt = runtime();
    let steps = Arc::new(Mutex::new(Vec::new()));
    let s = steps.clone();
    let gap = Duration::from_millis(20);
    let t = rt
        .add(
            "ticker",
            ActivitySpec::file_descriptor(None),
            rtt::InitialState::Stopped,
            move |_| Ok(Ticker { gap, steps: s }),
        )
        .unwrap();
    let started = Instant::now();
    t.start().unwrap();
    wait_for("five deadline steps", || steps.lock().unwrap().len() >= 5);
    t.stop().unwrap();
    let steps = steps.lock().unwrap().clone();
    assert!(
        steps.iter().all(|(_, d)| *d),
        "every step came from its deadline"
    );
    // A timer never fires early: each step at least one gap after the previous.
    let mut last = started;
    for (at, _) in &steps {
        assert!(
            at.duration_since(last) >= gap,
            "a step {:?} after the one before",
            at.duration_since(last)
        );
        last = *at;
    }
    // A deadline already past steps at once.
    assert!(t.activity().wake_at(rtt::time::Timestamp::ZERO).is_ok());
    let periodic = rt
        .add(
            "p",
            ActivitySpec::periodic(gap),
            rtt::InitialState::Stopped,
            |_| Ok(Nothing),
        )
        .unwrap();
    assert!(
        periodic
            .activity()
            .wake_at(rtt::time::Timestamp::ZERO)
            .is_err(),
        "only a file-descriptor activity has deadlines"
    );
}

/// Per step: (the deadline passed, the timeout fired, the pipe was ready).
type DeadlineSteps = Arc<Mutex<Vec<(bool, bool, bool)>>>;

/// Asks for a step at once from each of its steps until its pipe has been seen ready: a
/// line polling back to back.
struct BackToBack {
    pipe: std::fs::File,
    fd: i32,
    steps: DeadlineSteps,
}

impl Component for BackToBack {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        ctx.activity().watch(self.pipe.as_fd())?;
        Ok(())
    }

    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        ctx.activity().wake_at(rtt::time::Timestamp::ZERO)?;
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let ev = ctx.fd_events();
        let ready = ev.is_updated(self.fd);
        self.steps
            .lock()
            .unwrap()
            .push((ev.deadline_passed(), ev.has_timeout(), ready));
        if ready {
            let mut buf = [0u8; 16];
            std::io::Read::read(&mut self.pipe, &mut buf)?;
        } else {
            ctx.activity().wake_at(rtt::time::Timestamp::ZERO)?;
        }
        Ok(())
    }
}

#[test]
fn a_past_deadline_from_the_step_steps_again_at_once_and_still_sees_descriptors() {
    let (rx, tx) = std::io::pipe().unwrap();
    let rx: std::fs::File = std::os::fd::OwnedFd::from(rx).into();
    let mut tx: std::fs::File = std::os::fd::OwnedFd::from(tx).into();
    let steps = DeadlineSteps::default();
    let s = steps.clone();
    let fd = rx.as_raw_fd();
    let rt = runtime();
    let t = rt
        .add(
            "b2b",
            ActivitySpec::file_descriptor(Some(Duration::from_secs(60))),
            rtt::InitialState::PreOperational,
            move |_| {
                Ok(BackToBack {
                    pipe: rx,
                    fd,
                    steps: s,
                })
            },
        )
        .unwrap();
    t.configure().unwrap();
    t.start().unwrap();
    wait_for("100 steps back to back", || {
        steps.lock().unwrap().len() >= 100
    });
    tx.write_all(b"x").unwrap();
    wait_for("the pipe seen among them", || {
        steps.lock().unwrap().iter().any(|(_, _, ready)| *ready)
    });
    t.stop().unwrap();
    let steps = steps.lock().unwrap();
    let until = steps.iter().position(|(_, _, ready)| *ready).unwrap();
    assert!(
        steps[..until].iter().all(|(d, t, _)| *d && !*t),
        "every step before the pipe was a deadline step, none a timeout"
    );
}

/// Asks, at its first trigger, for a step `gap` later; at its second, for one at once.
struct Replacer {
    gap: Duration,
    triggers: u32,
    steps: DeadlineSteps,
}

impl Component for Replacer {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        use rtt::time::{Clock, MonotonicClock};
        let deadline = ctx.fd_events().deadline_passed();
        self.steps.lock().unwrap().push((deadline, false, false));
        if !deadline {
            self.triggers += 1;
            let at = match self.triggers {
                1 => MonotonicClock.now().saturating_add(self.gap),
                _ => rtt::time::Timestamp::ZERO,
            };
            ctx.activity().wake_at(at)?;
        }
        Ok(())
    }
}

#[test]
fn a_past_deadline_from_the_step_replaces_the_timer_armed_before() {
    let steps = DeadlineSteps::default();
    let s = steps.clone();
    let gap = Duration::from_millis(100);
    let rt = runtime();
    let t = rt
        .add(
            "replacer",
            ActivitySpec::file_descriptor(None),
            rtt::InitialState::Stopped,
            move |_| {
                Ok(Replacer {
                    gap,
                    triggers: 0,
                    steps: s,
                })
            },
        )
        .unwrap();
    t.start().unwrap();
    t.trigger();
    wait_for("the first trigger's step", || {
        !steps.lock().unwrap().is_empty()
    });
    let armed = Instant::now();
    t.trigger();
    wait_for("the second trigger's step and its step at once", || {
        steps.lock().unwrap().len() >= 3
    });
    assert!(
        armed.elapsed() < gap,
        "the check below needs the second trigger before the first deadline"
    );
    // The timer armed for `gap` after the first trigger was replaced: no step comes then.
    // (An absence, so a wait: three times the gap.)
    std::thread::sleep(gap * 3);
    t.stop().unwrap();
    let steps = steps.lock().unwrap();
    assert_eq!(
        steps.iter().map(|(d, _, _)| *d).collect::<Vec<_>>(),
        [false, false, true],
        "trigger, trigger, the step at once, and no deadline step after"
    );
}

/// Per step: when, and whether its deadline passed.
type StepLog = Arc<Mutex<Vec<(Instant, bool)>>>;

/// Records each step; asks for a step at once from every step while `again` is set.
struct Recorder {
    again: Arc<AtomicBool>,
    steps: StepLog,
}

impl Component for Recorder {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let deadline = ctx.fd_events().deadline_passed();
        self.steps.lock().unwrap().push((Instant::now(), deadline));
        if self.again.load(Ordering::SeqCst) {
            ctx.activity().wake_at(rtt::time::Timestamp::ZERO)?;
        }
        Ok(())
    }
}

fn recorder(rt: &Runtime, name: &str, again: bool) -> (rtt::TaskContext, Arc<AtomicBool>, StepLog) {
    let again = Arc::new(AtomicBool::new(again));
    let steps = Arc::new(Mutex::new(Vec::new()));
    let (a, s) = (again.clone(), steps.clone());
    let t = rt
        .add(
            name,
            ActivitySpec::file_descriptor(None),
            rtt::InitialState::Stopped,
            move |_| Ok(Recorder { again: a, steps: s }),
        )
        .unwrap();
    (t, again, steps)
}

#[test]
fn a_deadline_from_another_thread_steps_then_and_not_before() {
    use rtt::time::{Clock, MonotonicClock};
    let rt = runtime();
    let (t, _, steps) = recorder(&rt, "asked", false);
    t.start().unwrap();
    let gap = Duration::from_millis(50);
    let asked = Instant::now();
    t.activity()
        .wake_at(MonotonicClock.now().saturating_add(gap))
        .unwrap();
    wait_for("the deadline step", || !steps.lock().unwrap().is_empty());
    let (at, deadline) = steps.lock().unwrap()[0];
    assert!(
        deadline,
        "the first step is the deadline's, not the request's wake-up"
    );
    assert!(at.duration_since(asked) >= gap, "not before the deadline");
    // A time already past, from another thread: a step at once.
    t.activity().wake_at(rtt::time::Timestamp::ZERO).unwrap();
    wait_for("the step at once", || steps.lock().unwrap().len() >= 2);
    assert!(steps.lock().unwrap()[1].1);
    t.stop().unwrap();
}

#[test]
fn a_step_due_at_once_when_stopped_comes_at_the_next_start() {
    let rt = runtime();
    let (t, again, steps) = recorder(&rt, "restart", true);
    t.start().unwrap();
    t.trigger();
    wait_for("steps back to back", || steps.lock().unwrap().len() >= 10);
    t.stop().unwrap();
    again.store(false, Ordering::SeqCst);
    steps.lock().unwrap().clear();
    t.start().unwrap();
    wait_for("the step asked for before the stop", || {
        !steps.lock().unwrap().is_empty()
    });
    assert!(steps.lock().unwrap()[0].1, "it is a deadline step");
    t.stop().unwrap();
}

struct Nothing;
impl Component for Nothing {}
