//! The shared fault policy on the IO components (a card's `faults`): a simulated card gone
//! offline raises the sampling component's warning at the first missed sample and puts it
//! in RunTimeError at the fifth; the card back, it is Running without the warning, by
//! itself. Without `faults` nothing changes state (the device's health tells).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::Registry;
use driver_sim::{SimCard, SimConfig, SimFault};
use rtt::faults::FaultPolicy;
use rtt::{Runtime, RuntimeOptions, TaskState};
use std::sync::Arc;
use std::time::Duration;
use testkit::wait_until;

fn sampled(policy: FaultPolicy) -> (Arc<SimCard>, rtt::TaskContext, Runtime) {
    let registry = Arc::new(Registry::new());
    let card = SimCard::new(&SimConfig::demo(), Arc::new(rtt::time::MonotonicClock)).unwrap();
    card.register(&registry, "sim").unwrap();
    card.step();
    let rt = Runtime::new(registry, RuntimeOptions::default()).unwrap();
    let tasks = hwgw::io::build(
        &rt,
        "sim",
        (Duration::from_millis(5), policy),
        &Default::default(),
        &Default::default(),
    )
    .unwrap();
    let ai = tasks.into_iter().find(|t| t.name() == "sim.ai").unwrap();
    ai.start().unwrap();
    (card, ai, rt)
}

#[test]
fn an_offline_card_warns_then_errs_and_recovers_by_itself() {
    let (card, ai, _rt) = sampled(FaultPolicy::default());
    wait_until("steps", || ai.stats().steps > 2);
    assert!(!ai.counters().warning);
    card.set_fault(SimFault::Offline);
    wait_until("RunTimeError", || ai.state() == TaskState::RunTimeError);
    let c = ai.counters();
    assert!(
        c.warning && c.warnings == 1 && c.runtime_errors == 1,
        "{c:?}"
    );
    card.set_fault(SimFault::None);
    // The card's own step refreshes its inputs (this test plays its bus activity).
    wait_until("Running again", || {
        card.step();
        ai.state() == TaskState::Running
    });
    assert!(!ai.counters().warning);
}

#[test]
fn without_a_policy_the_state_stays() {
    let (card, ai, _rt) = sampled(FaultPolicy::NEVER);
    card.set_fault(SimFault::Offline);
    let steps = ai.stats().steps;
    wait_until("ten samples of an offline card", || {
        ai.stats().steps > steps + 10
    });
    assert_eq!(ai.state(), TaskState::Running);
    assert!(!ai.counters().warning);
}
