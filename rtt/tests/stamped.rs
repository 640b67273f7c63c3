//! Stamped buffer connections carry the time each sample was written, on the clock the
//! connection was made with, through the typed and the dynamic ports; a data policy is
//! refused; a full buffer counts what it lost. Step taps see each step's times.

use device_interface::Registry;
use device_interface::time::{Clock, SimClock, Timestamp};
use rtt::port::{ConnPolicy, ConnectError, FlowStatus, InputPort, OutputPort, connect_stamped};
use rtt::{ActivitySpec, Component, Context, HookResult, InitialState, Runtime, RuntimeOptions};
use std::sync::Arc;
use std::time::Duration;

#[test]
fn each_sample_carries_the_time_it_was_written() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000)));
    let mut out = OutputPort::<f64>::new("out");
    let mut inp = InputPort::<f64>::new("in");
    connect_stamped(&out, &inp, ConnPolicy::buffer(8), clock.clone()).expect("buffer");
    for v in [1.0, 2.0, 3.0] {
        out.write(&v);
        clock.advance(Duration::from_micros(250));
    }
    let (mut x, mut at) = (0.0, 0);
    let mut got = Vec::new();
    while inp.read_at(&mut x, &mut at) == FlowStatus::NewData {
        got.push((x, at));
    }
    assert_eq!(got, vec![(1.0, 1_000), (2.0, 251_000), (3.0, 501_000)]);
}

#[test]
fn a_data_policy_cannot_be_stamped() {
    let out = OutputPort::<f64>::new("out");
    let inp = InputPort::<f64>::new("in");
    let clock: Arc<dyn Clock> = Arc::new(SimClock::default());
    assert_eq!(
        connect_stamped(&out, &inp, ConnPolicy::data(), clock),
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
fn the_dynamic_reader_gives_stamps_and_counts_losses_and_the_tap_gives_steps() {
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(5)));
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
    let mut r = port
        .stamped_reader(ConnPolicy::buffer(3), clock.clone())
        .expect("stamped");
    let tap = task.activity().tap_steps(16);
    task.start().expect("start");
    for _ in 0..5 {
        task.step().expect("step");
        clock.advance(Duration::from_millis(1));
    }
    let mut got = Vec::new();
    while let (FlowStatus::NewData, Some(v), at) = r.read_at() {
        got.push((v, at));
    }
    assert_eq!(
        got,
        vec![
            (serde_json::json!(1), 5),
            (serde_json::json!(2), 1_000_005),
            (serde_json::json!(3), 2_000_005),
        ]
    );
    assert_eq!(r.dropped(), 2, "two samples did not fit a buffer of three");
    let mut steps = Vec::new();
    tap.drain(&mut steps);
    assert_eq!(steps.len(), 5);
    assert!(steps.windows(2).all(|w| w[0].ended <= w[1].started));
    assert!(
        steps
            .iter()
            .all(|s| s.scheduled <= s.started && s.started <= s.ended)
    );
}
