//! A triggered capture fed as the gateway feeds it — port after port within a batch, a
//! batch longer than the window's slack, ports that fall silent after the trigger — holds
//! exactly its window and ends.

use recording::read::Recording;
use recording::{Capture, Closing, Item, Options, PortSpec, Recorder, Trigger, Window};
use serde_json::json;
use std::io::Cursor;

const MS: u64 = 1_000_000;

fn ports() -> Vec<PortSpec> {
    ["a.fast", "b.level"]
        .iter()
        .map(|n| PortSpec {
            name: (*n).into(),
            type_name: "f64".into(),
        })
        .collect()
}

/// A batch of `secs` s: port 0 every 1 ms, then port 1 every 10 ms, rising above 0.5 at
/// t = 1.5 s.
fn batch(secs: u64) -> Vec<Item> {
    let mut batch = Vec::new();
    for k in 0..secs * 1_000 {
        batch.push(Item::Sample {
            port: 0,
            at_ns: k * MS,
            value: json!(k),
        });
    }
    for k in 0..secs * 100 {
        let v = if k >= 150 { 1.0 } else { 0.0 };
        batch.push(Item::Sample {
            port: 1,
            at_ns: k * 10 * MS,
            value: json!(v),
        });
    }
    batch
}

fn check(out: &Cursor<Vec<u8>>) {
    let rec = Recording::parse(out.get_ref()).expect("readable");
    let fast = &rec.ports[0].points;
    assert_eq!(
        fast.len(),
        301,
        "1 ms samples from 1.4 s to 1.7 s inclusive"
    );
    assert_eq!((fast[0].0, fast[300].0), (1_400 * MS, 1_700 * MS));
    assert_eq!(rec.ports[1].points.len(), 31);
}

#[test]
fn a_batch_far_longer_than_the_slack_in_port_order_loses_nothing_of_the_window() {
    let mut out = Cursor::new(Vec::new());
    let rec = Recorder::new(&mut out, ports(), vec![], Options::default()).expect("new");
    let trigger: Trigger = "b.level > 0.5".parse().expect("valid");
    let window = Window::new(trigger, 1, 100 * MS, 200 * MS, 1 << 20);
    let mut cap = Capture::new(rec, Some(window));
    // A drain that came 4 s late: port 0's samples up to 4 s come before port 1's edge.
    cap.offer(batch(4), 4_000 * MS).expect("offer");
    assert!(cap.done());
    let meta = cap.finish(Closing::default()).expect("finish");
    assert_eq!(meta["trigger.ring_overflow"], "0");
    assert_eq!(meta["trigger.complete_from_ns"], (1_400 * MS).to_string());
    check(&out);
}

#[test]
fn an_edge_before_pre_of_history_has_come_is_not_taken() {
    let mut out = Cursor::new(Vec::new());
    let rec = Recorder::new(&mut out, ports(), vec![], Options::default()).expect("new");
    let trigger: Trigger = "b.level > 0.5".parse().expect("valid");
    // pre 2 s: the edge at 1.5 s comes before 2 s of history, so it does not trigger.
    let window = Window::new(trigger, 1, 2_000 * MS, 200 * MS, 1 << 20);
    let mut cap = Capture::new(rec, Some(window));
    cap.offer(batch(3), 3_000 * MS).expect("offer");
    assert!(!cap.triggered());
    let meta = cap.finish(Closing::default()).expect("finish");
    assert_eq!(meta["trigger.at_ns"], "never");
}

#[test]
fn ports_that_fall_silent_after_the_trigger_still_end_the_window() {
    let mut out = Cursor::new(Vec::new());
    let rec = Recorder::new(&mut out, ports(), vec![], Options::default()).expect("new");
    let trigger: Trigger = "b.level > 0.5".parse().expect("valid");
    let window = Window::new(trigger, 1, 100 * MS, 200 * MS, 1 << 20);
    let mut cap = Capture::new(rec, Some(window));
    cap.offer(batch(2), 2_000 * MS).expect("offer");
    assert!(cap.triggered() && !cap.done());
    // The ports fall silent: time going on ends the window.
    cap.offer(Vec::new(), 2_300 * MS).expect("offer");
    assert!(cap.done());
    let meta = cap.finish(Closing::default()).expect("finish");
    assert_eq!(meta["trigger.at_ns"], (1_500 * MS).to_string());
    assert_eq!(meta["trigger.complete_from_ns"], (1_400 * MS).to_string());
    assert_eq!(meta["trigger.ring_overflow"], "0");
    check(&out);
}
