//! Activities on real threads: fd wake-up and timeout, deadlines (`deadlines/`, here as
//! the kernel gives them), overrun counting and health, a stop cut short however long the
//! period,
//! SCHED_FIFO fallback, and ThreadScope pulses read back from a sim card's output record.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use driver_sim::{OutputWrite, SimCard, SimConfig};
use rtt::activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
use rtt::{Component, Context, HookResult, Runtime, RuntimeOptions};
use std::collections::BTreeMap;
use std::io::Write;
use std::os::fd::{AsFd, AsRawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::wait_until as wait_for;

mod deadlines;

fn runtime() -> Runtime {
    // The deadline tests' threads are SCHED_OTHER: they wait as a real-time one would.
    rtt::activity::use_precise_deadlines_for_every_thread();
    Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap()
}

/// Per step: (the pipe was ready, the timeout fired, the bytes read).
type Steps = Arc<Mutex<Vec<(bool, bool, Vec<u8>)>>>;

#[test]
fn fd_activity_wakes_on_data_and_on_timeout() {
    struct Reader {
        pipe: std::fs::File,
        fd: i32,
        seen: Steps,
    }
    impl Component for Reader {
        fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
            ctx.activity().watch(self.pipe.as_fd())?;
            Ok(())
        }
        fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
            let ev = ctx.fd_events();
            let mut data = Vec::new();
            if ev.is_updated(self.fd) {
                let mut buf = [0u8; 64];
                let n = std::io::Read::read(&mut self.pipe, &mut buf)?;
                data.extend_from_slice(&buf[..n]);
            }
            self.seen
                .lock()
                .unwrap()
                .push((ev.is_updated(self.fd), ev.has_timeout(), data));
            Ok(())
        }
    }
    let (rx, tx) = std::io::pipe().unwrap();
    let rx: std::fs::File = std::os::fd::OwnedFd::from(rx).into();
    let mut tx: std::fs::File = std::os::fd::OwnedFd::from(tx).into();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let rt = runtime();
    let s = seen.clone();
    let fd = rx.as_raw_fd();
    let t = rt
        .add(
            "reader",
            ActivitySpec::file_descriptor(Some(Duration::from_millis(50))),
            rtt::InitialState::PreOperational,
            move |_| {
                Ok(Reader {
                    pipe: rx,
                    fd,
                    seen: s,
                })
            },
        )
        .unwrap();
    t.configure().unwrap();
    t.start().unwrap();
    tx.write_all(b"hello").unwrap();
    wait_for("the data step", || {
        seen.lock()
            .unwrap()
            .iter()
            .any(|(u, _, d)| *u && d == b"hello")
    });
    wait_for("a timeout step", || {
        seen.lock().unwrap().iter().any(|(u, t, _)| !*u && *t)
    });
    t.stop().unwrap();
    let seen = seen.lock().unwrap();
    assert!(
        seen.iter().all(|(u, t, _)| !(*u && *t)),
        "a step is either data or timeout"
    );
    assert!(!t.activity().unwatch(999));
}

struct Sleepy {
    sleep: Arc<AtomicBool>,
}
impl Component for Sleepy {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if self.sleep.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(6));
        }
        Ok(())
    }
}

/// A stopped `Sleepy` on a 2 ms period, unhealthy after `max_overruns`, sleeping through
/// its steps until the flag returned says otherwise.
fn sleepy(rt: &Runtime, max_overruns: u32) -> (rtt::TaskContext, Arc<AtomicBool>) {
    let sleep = Arc::new(AtomicBool::new(true));
    let s = sleep.clone();
    let spec = ActivitySpec::Periodic {
        period: Duration::from_millis(2),
        thread: ThreadOptions::default(),
        timing: Timing::Absolute,
        max_overruns: Some(max_overruns),
    };
    let t = rt
        .add("sleepy", spec, rtt::InitialState::Stopped, move |_| {
            Ok(Sleepy { sleep: s })
        })
        .unwrap();
    (t, sleep)
}

#[test]
fn overruns_are_counted_and_turn_health_off_then_on() {
    let rt = runtime();
    let (t, sleep) = sleepy(&rt, 3);
    t.start().unwrap();
    wait_for("5 overruns", || t.stats().overruns >= 5);
    let unhealthy = t.stats();
    assert!(!unhealthy.healthy, "more than 3 overruns in a row");
    assert_eq!(unhealthy.unhealthy_spells, 1);
    // The spell's time runs on while it is on.
    wait_for("the spell's time to grow", || {
        t.stats().unhealthy_ns > unhealthy.unhealthy_ns
    });
    sleep.store(false, Ordering::SeqCst);
    wait_for("health back", || t.stats().healthy);
    let before = t.stats();
    assert!(before.unhealthy_ns > unhealthy.unhealthy_ns);
    std::thread::sleep(Duration::from_millis(20));
    t.stop().unwrap();
    let after = t.stats();
    assert!(after.steps > before.steps);
    assert!(after.overruns >= 5);
    assert!(after.step_max_ns >= 6_000_000);
}

/// A spell on when the activity stops ends there: a stopped activity is healthy, and its
/// unhealthy time does not run on while it is stopped.
#[test]
fn a_stop_ends_a_spell_of_overruns() {
    let rt = runtime();
    let (t, _sleep) = sleepy(&rt, 1);
    t.start().unwrap();
    wait_for("a spell", || !t.stats().healthy);
    t.stop().unwrap();
    let stopped = t.stats();
    assert!(stopped.healthy, "{stopped:?}");
    assert!(stopped.unhealthy_ns > 0, "{stopped:?}");
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(t.stats().unhealthy_ns, stopped.unhealthy_ns);
}

#[test]
fn a_long_period_does_not_hold_up_a_stop() {
    struct Idle;
    impl Component for Idle {}
    let rt = runtime();
    let spec = ActivitySpec::Periodic {
        period: Duration::from_secs(24 * 3600),
        thread: ThreadOptions::default(),
        timing: Timing::Absolute,
        max_overruns: None,
    };
    let t = rt
        .add("daily", spec, rtt::InitialState::Stopped, |_| Ok(Idle))
        .unwrap();
    t.start().unwrap();
    wait_for("the first step", || t.stats().steps == 1);
    // The activity now sleeps until tomorrow; a stop must not wait for that.
    let (tx, rx) = std::sync::mpsc::channel();
    let task = t.clone();
    std::thread::spawn(move || tx.send(task.stop().is_ok()).unwrap());
    assert_eq!(
        rx.recv_timeout(Duration::from_secs(30)),
        Ok(true),
        "the stop waited for the next period"
    );
    assert_eq!(t.state(), rtt::TaskState::Stopped);
    assert_eq!(t.stats().steps, 1);
}

#[test]
fn refused_fifo_falls_back_to_other_and_still_runs() {
    let rt = runtime();
    let fifo = |priority| ActivitySpec::Periodic {
        period: Duration::from_millis(1),
        thread: ThreadOptions {
            policy: SchedPolicy::Fifo,
            priority,
            cpus: vec![0],
            ..ThreadOptions::default()
        },
        timing: Timing::Relative,
        max_overruns: None,
    };
    // Priority 100 is outside SCHED_FIFO's 1..=99: refused when the component is made,
    // with the reason, rather than found at run time.
    let invalid = rt.add("invalid", fifo(100), rtt::InitialState::Stopped, |_| {
        Ok(Sleepy {
            sleep: Arc::new(AtomicBool::new(false)),
        })
    });
    assert_eq!(
        invalid.unwrap_err().to_string(),
        "component \"invalid\": priority 100: SCHED_FIFO takes 1 to 99"
    );
    // A valid priority runs whether or not the kernel grants it (without CAP_SYS_NICE or an
    // RLIMIT_RTPRIO it falls back to SCHED_OTHER and says so once).
    let refused = rt
        .add("refused", fifo(99), rtt::InitialState::Stopped, |_| {
            Ok(Sleepy {
                sleep: Arc::new(AtomicBool::new(false)),
            })
        })
        .unwrap();
    refused.start().unwrap();
    wait_for("20 steps", || refused.stats().steps >= 20);
    refused.stop().unwrap();
    let stats = refused.stats();
    let total: u64 = stats.lateness_histogram.iter().sum();
    assert_eq!(total, stats.steps, "every wake-up is in the histogram");
}

/// A runtime with ThreadScope on a simulated card of 16 outputs that records every write.
fn scope_runtime() -> (Arc<SimCard>, Runtime) {
    let registry = Arc::new(Registry::new());
    let mut config = SimConfig::demo();
    config.digital_outputs = 16;
    config.record_capacity = 1 << 20;
    let card = SimCard::new(&config, Arc::new(rtt::time::MonotonicClock)).unwrap();
    card.register(&registry, "sim").unwrap();
    registry.digital_out().alias("ThreadScope", "sim").unwrap();
    let rt = Runtime::new(
        registry,
        RuntimeOptions {
            thread_scope: true,
            ..Default::default()
        },
    )
    .unwrap();
    (card, rt)
}

#[test]
fn thread_scope_pulses_each_thread_bit_in_order() {
    struct Busy(Arc<AtomicU64>);
    impl Component for Busy {
        fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
            self.0.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
    }
    let (card, rt) = scope_runtime();
    let steps = Arc::new(AtomicU64::new(0));
    let mk = |name: &str, spec: ActivitySpec| {
        let s = steps.clone();
        rt.add(name, spec, rtt::InitialState::Stopped, move |_| Ok(Busy(s)))
            .unwrap()
    };
    let fast = mk("fast", ActivitySpec::periodic(Duration::from_millis(1)));
    let slow = mk("slow", ActivitySpec::periodic(Duration::from_millis(3)));
    let evented = mk("evented", ActivitySpec::non_periodic());
    let slave = mk("slave", ActivitySpec::Slave);
    assert_eq!(
        (
            fast.activity().thread_number(),
            slow.activity().thread_number(),
            evented.activity().thread_number(),
            slave.activity().thread_number()
        ),
        (Some(1), Some(2), Some(3), None),
        "threads numbered in creation order; a slave has no thread"
    );
    for t in [&fast, &slow, &evented, &slave] {
        t.start().unwrap();
    }
    for _ in 0..30 {
        evented.trigger();
        slave.step().unwrap(); // on the main thread: bit 0
        std::thread::sleep(Duration::from_millis(2));
    }
    for t in [&fast, &slow, &evented, &slave] {
        t.stop().unwrap();
    }
    assert_eq!(card.output_record_dropped(), 0);
    let mut per_bit: BTreeMap<u32, Vec<bool>> = BTreeMap::new();
    for e in card.take_output_record() {
        if let OutputWrite::Bit { bit, value } = e.write {
            per_bit.entry(bit).or_default().push(value);
        }
    }
    assert_eq!(
        per_bit.keys().copied().collect::<Vec<_>>(),
        vec![0, 1, 2, 3],
        "bits as numbered"
    );
    for (bit, values) in &per_bit {
        assert!(values.len() >= 2, "bit {bit} pulsed");
        for (i, v) in values.iter().enumerate() {
            assert_eq!(
                *v,
                i % 2 == 0,
                "bit {bit}: high, low, high, low … never two highs in a row"
            );
        }
        assert_eq!(values.last(), Some(&false), "bit {bit} ends low");
    }
    assert_eq!(per_bit[&0].len(), 60, "30 slave steps on the main thread");
    assert_eq!(rt.thread_scope().errors(), 0);
}

#[test]
fn thread_scope_closed_waits_for_its_pulses_and_writes_no_more() {
    struct Slow;
    impl Component for Slow {
        fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
            std::thread::sleep(Duration::from_millis(5));
            Ok(())
        }
    }
    let (card, rt) = scope_runtime();
    let t = rt
        .add(
            "slow",
            ActivitySpec::periodic(Duration::from_millis(1)),
            rtt::InitialState::Stopped,
            |_| Ok(Slow),
        )
        .unwrap();
    t.start().unwrap();
    // Two steps under way or done (not a sleep: a loaded machine may start it late).
    let end = Instant::now() + Duration::from_secs(20);
    while t.stats().steps < 2 {
        assert!(Instant::now() < end, "the slow component never stepped");
        std::thread::sleep(Duration::from_millis(1));
    }
    // Closed in the middle of a 5 ms step: it waits for that step's low.
    assert!(
        rt.thread_scope()
            .close(Instant::now() + Duration::from_secs(1))
    );
    let record = card.take_output_record();
    let last = record.iter().rev().find_map(|e| match e.write {
        OutputWrite::Bit { bit: 1, value } => Some(value),
        _ => None,
    });
    assert_eq!(last, Some(false), "bit 1 ends low");
    // The thread steps on; its bit is not written any more.
    std::thread::sleep(Duration::from_millis(20));
    assert!(card.take_output_record().is_empty());
    t.stop().unwrap();
}

#[test]
fn thread_scope_needs_its_output() {
    let e = Runtime::new(
        Arc::new(Registry::new()),
        RuntimeOptions {
            thread_scope: true,
            ..Default::default()
        },
    )
    .err()
    .unwrap();
    assert_eq!(
        e.to_string(),
        "ThreadScope is on, but no DigitalOut named \"ThreadScope\"; registered: none"
    );
}

/// A spin beyond 10 ms is refused; 0 (park at once) and the default are taken.
#[test]
fn spin_is_bounded() {
    let mut t = ThreadOptions {
        spin_us: rtt::activity::MAX_SPIN_US + 1,
        ..ThreadOptions::default()
    };
    let e = t.check().unwrap_err();
    assert_eq!(e, rtt::activity::ThreadError::Spin(10_001));
    assert!(e.to_string().contains("at most 10000"), "{e}");
    t.spin_us = 0;
    assert!(t.check().is_ok());
    assert_eq!(
        ThreadOptions::default().spin_us,
        rtt::activity::DEFAULT_SPIN_US
    );
}

/// Waits 60 ms in its own code at each step, then restarts the step's clock and ends.
struct WaitsThenWorks {
    at: Arc<Mutex<Vec<(u64, u64)>>>,
}

impl Component for WaitsThenWorks {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        std::thread::sleep(Duration::from_millis(60));
        let before = rtt::activity::stamp_now();
        ctx.activity().restart_step();
        self.at
            .lock()
            .unwrap()
            .push((before, rtt::activity::stamp_now()));
        Ok(())
    }
}

#[test]
fn a_step_that_restarts_its_clock_counts_from_there() {
    let rt = runtime();
    let at = Arc::new(Mutex::new(Vec::new()));
    let a = at.clone();
    let t = rt
        .add(
            "waits",
            ActivitySpec::file_descriptor(None),
            rtt::InitialState::Stopped,
            move |_| Ok(WaitsThenWorks { at: a }),
        )
        .unwrap();
    t.start().unwrap();
    t.trigger();
    wait_for("a step", || t.stats().steps >= 1);
    t.stop().unwrap();
    let stats = t.stats();
    // The 60 ms waited are not the step's: what is left is the push after the restart.
    assert!(
        stats.step_max_ns < 50_000_000,
        "the wait was counted: longest step {} ns",
        stats.step_max_ns
    );
    let (before, after) = at.lock().unwrap()[0];
    assert!(
        after >= before + 50_000_000,
        "the stamp after the restart is the restart's time: {before} then {after}"
    );
    // Outside a step (this thread): nothing happens.
    t.activity().restart_step();
}
