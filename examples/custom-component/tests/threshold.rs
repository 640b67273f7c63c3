//! The example type works inside a real deployment.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use rtt::port::{ConnPolicy, FlowStatus};
use std::time::{Duration, Instant};

#[test]
fn threshold_switches_the_digital_output_both_ways() {
    let text = include_str!("../threshold.toml");
    let d = Deployment::parse(text, "threshold.toml").unwrap();
    let gw = Gateway::build(&d, "threshold.toml", text, &hwgw_example_custom::types()).unwrap();
    let mut seen = gw
        .runtime()
        .component("sim0.di")
        .unwrap()
        .port("bit0")
        .unwrap()
        .reader(ConnPolicy::buffer(1024))
        .unwrap();
    gw.start().unwrap();
    let (mut on, mut off) = (false, false);
    let deadline = Instant::now() + Duration::from_secs(10);
    while !(on && off) {
        assert!(
            Instant::now() < deadline,
            "the output did not switch both ways (on {on}, off {off})"
        );
        while let (FlowStatus::NewData, Some(v)) = seen.read() {
            if v.as_bool() == Some(true) {
                on = true;
            } else if on {
                off = true;
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let is_on = gw
        .runtime()
        .component("threshold")
        .unwrap()
        .operation::<(), bool>("is_on")
        .unwrap();
    is_on.call(()).unwrap();
    gw.shutdown();
}

#[test]
fn the_builtin_types_are_still_there_and_names_are_unique() {
    let mut t = hwgw_example_custom::types().components;
    assert_eq!(
        t.names(),
        vec![
            "blinker",
            "follow",
            "recorder",
            "reporter",
            "scan",
            "script",
            "supervisor",
            "threshold"
        ]
    );
    assert!(!t.register("follow", |rt, name, spec| rt.add(
        name,
        spec,
        rtt::InitialState::Stopped,
        |_| Ok(Nothing)
    )));
}

struct Nothing;
impl rtt::Component for Nothing {}
