//! Stamped buffer connections carry the time each sample was written — the start of the
//! step that wrote it, or the monotonic clock outside a step — through the typed and the
//! dynamic ports; a data policy is refused; a full buffer counts what it lost. Step taps
//! see each step's times. A journal tap's entries carry them too, in one lane a component
//! keeps across restarts.

use device_interface::Registry;
use device_interface::time::{Clock, MonotonicClock};
use rtt::port::{ConnPolicy, ConnectError, FlowStatus, InputPort, OutputPort, connect_stamped};
use rtt::{ActivitySpec, Component, Context, HookResult, InitialState, Runtime, RuntimeOptions};
use std::sync::Arc;
use std::time::Duration;

#[test]
fn outside_a_step_each_sample_carries_the_time_it_was_written() {
    let mut out = OutputPort::<f64>::new("out");
    let mut inp = InputPort::<f64>::new("in");
    connect_stamped(&out, &inp, ConnPolicy::buffer(8)).expect("buffer");
    let mut bounds = Vec::new();
    for v in [1.0, 2.0, 3.0] {
        let before = MonotonicClock.now().as_nanos();
        out.write(&v);
        bounds.push((before, MonotonicClock.now().as_nanos()));
        std::thread::sleep(Duration::from_micros(200));
    }
    let (mut x, mut at) = (0.0, 0);
    let mut got = Vec::new();
    while inp.read_at(&mut x, &mut at) == FlowStatus::NewData {
        got.push((x, at));
    }
    assert_eq!(got.iter().map(|g| g.0).collect::<Vec<_>>(), [1.0, 2.0, 3.0]);
    for ((_, at), (before, after)) in got.iter().zip(&bounds) {
        assert!(
            (before..=after).contains(&at),
            "{before} <= {at} <= {after}"
        );
    }
}

#[test]
fn a_data_policy_cannot_be_stamped() {
    let out = OutputPort::<f64>::new("out");
    let inp = InputPort::<f64>::new("in");
    assert_eq!(
        connect_stamped(&out, &inp, ConnPolicy::data()),
        Err(ConnectError::NotBuffered)
    );
}

struct Counter {
    out: OutputPort<u32>,
    n: u32,
}

impl Component for Counter {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.n += 1;
        self.out.write(&self.n);
        Ok(())
    }
}

#[test]
fn in_a_step_samples_carry_the_steps_start_and_the_tap_gives_the_steps() {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).expect("runtime");
    let task = rt
        .add("counter", ActivitySpec::Slave, InitialState::Stopped, |i| {
            Ok(Counter {
                out: i.output("out", "steps so far")?,
                n: 0,
            })
        })
        .expect("component");
    let port = task.port("out").expect("port");
    let mut r = port.stamped_reader(ConnPolicy::buffer(3)).expect("stamped");
    let tap = task.activity().tap_steps(16);
    task.start().expect("start");
    for _ in 0..5 {
        task.step().expect("step");
        std::thread::sleep(Duration::from_micros(100));
    }
    let mut got = Vec::new();
    while let (FlowStatus::NewData, Some(v), at) = r.read_at() {
        got.push((v, at));
    }
    let mut steps = Vec::new();
    tap.drain(&mut steps);
    assert_eq!(steps.len(), 5);
    let want: Vec<_> = (1..=3)
        .map(|n| (serde_json::json!(n), steps[n - 1].started))
        .collect();
    assert_eq!(got, want, "each sample has its step's start");
    assert_eq!(r.dropped(), 2, "two samples did not fit a buffer of three");
    assert!(steps.windows(2).all(|w| w[0].ended <= w[1].started));
    assert!(
        steps
            .iter()
            .all(|s| s.scheduled <= s.started && s.started <= s.ended)
    );
}

/// A journal tap (a recording's) stamps each entry with its step's start too, and a
/// component's steps keep one lane of the journal across stops and starts — each start a
/// new thread — so none of its writes is dropped for want of a lane.
#[test]
fn a_journal_keeps_a_components_steps_in_one_lane_across_restarts() {
    use rtt::port::journal::Journal;
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).expect("runtime");
    let task = rt
        .add(
            "counter",
            ActivitySpec::non_periodic(),
            InitialState::Stopped,
            |i| {
                Ok(Counter {
                    out: i.output("out", "steps so far")?,
                    n: 0,
                })
            },
        )
        .expect("component");
    let journal = Arc::new(Journal::new(64));
    let (tap, value) = task
        .port("out")
        .expect("port")
        .tap(&journal, 7, "recording")
        .expect("a one-word port taps");
    let steps = task.activity().tap_steps(64);
    let mut seen = Vec::new();
    for round in 1..=6 {
        task.start().expect("start");
        task.trigger();
        testkit::wait_until("the triggered step", || {
            steps.drain(&mut seen);
            seen.len() >= round
        });
        task.stop().expect("stop");
    }
    steps.drain(&mut seen);
    let mut got = Vec::new();
    let mut stamps = Vec::new();
    journal.drain(usize::MAX, |e| {
        got.push((e.tap, value(e.word)));
        stamps.push(e.at);
    });
    assert_eq!(
        stamps,
        seen.iter().map(|s| s.started).collect::<Vec<_>>(),
        "each entry has its step's start"
    );
    assert_eq!(journal.dropped(), 0, "six threads, one lane");
    assert!(got.len() >= 6, "{got:?}");
    assert!(got.iter().all(|(t, _)| *t == 7));
    assert_eq!(
        got.iter().map(|(_, v)| v.clone()).collect::<Vec<_>>(),
        (1..=got.len() as u64)
            .map(|n| Some(serde_json::json!(n)))
            .collect::<Vec<_>>(),
        "in order"
    );
    drop(tap);
}
