//! The shared fault policy on the IO components (a card's `faults`): a simulated card gone
//! offline raises the sampling component's warning at the first missed sample and puts it
//! in RunTimeError at the fifth; the card back, it is Running without the warning, by
//! itself. Without `faults` nothing changes state (the device's health tells). And the
//! gateway's health, which feeds the systemd watchdog: a warning is healthy, RunTimeError
//! is not.

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

/// Raises a warning, goes to RunTimeError or recovers, as its property `mode` says.
struct Moody {
    mode: rtt::property::Property<String>,
}

impl rtt::Component for Moody {
    fn update_hook(&mut self, ctx: &mut rtt::Context<'_>) -> rtt::HookResult {
        match self.mode.get().as_str() {
            "warn" => ctx.warning(),
            "error" => ctx.error(),
            _ => ctx.recovered(),
        }
        Ok(())
    }

    fn error_hook(&mut self, ctx: &mut rtt::Context<'_>) {
        if self.mode.get() != "error" {
            ctx.recovered();
        }
    }
}

#[test]
fn the_watchdogs_health_takes_a_warning_as_healthy_and_an_error_as_not() {
    let mut types = hwgw::types::Types::builtin();
    types.components.register("moody", |rt, name, spec| {
        rt.add(name, spec, rtt::InitialState::Stopped, |i| {
            Ok(Moody {
                mode: i
                    .properties()
                    .add("mode", "ok".to_string(), "ok, warn or error")?,
            })
        })
    });
    let text = "[[component]]\nname = \"m\"\ntype = \"moody\"\nactivity = { type = \"periodic\", period_ms = 50 }\n";
    let d = hwgw::config::Deployment::parse(text, "m.toml").unwrap();
    let gw = hwgw::deploy::Gateway::build(&d, "m.toml", text, &types)
        .unwrap_or_else(|p| panic!("{p:?}"));
    gw.start().unwrap();
    let m = gw.runtime().component("m").unwrap();
    assert_eq!(gw.health(), Ok(()));
    let mode = |v: &str| {
        m.properties()
            .set_value("mode", serde_json::json!(v))
            .unwrap()
    };

    mode("warn");
    wait_until("the warning raised", || m.counters().warning);
    assert_eq!(m.state(), TaskState::Running);
    assert_eq!(gw.health(), Ok(()), "a warning is healthy");

    mode("error");
    wait_until("RunTimeError", || m.state() == TaskState::RunTimeError);
    let health = gw.health();
    assert!(
        health
            .as_ref()
            .is_err_and(|e| e.contains("m is in RunTimeError")),
        "{health:?}"
    );

    mode("ok");
    wait_until("Running again", || m.state() == TaskState::Running);
    assert_eq!(gw.health(), Ok(()));
    drop(gw.shutdown());
}
