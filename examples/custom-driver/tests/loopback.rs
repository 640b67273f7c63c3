//! The example driver: its card keeps the device contract (the conformance kit), and it
//! runs in a real `hwgw` — built from a deployment, read and written over the control
//! socket, its section's errors located in the file, its outputs safe at SIGTERM.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::conformance;
use device_interface::time::MonotonicClock;
use device_interface::{AnalogOut, DigitalOut};
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use hwgw_example_driver::{Loopback, LoopbackConfig};
use std::sync::Arc;
use testkit::{Service, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw-example-driver");
const DEPLOYMENT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/loopback.toml");

fn config(text: &str) -> LoopbackConfig {
    toml::from_str(text).unwrap()
}

#[test]
fn the_card_keeps_the_device_contract() {
    let card = Loopback::new(
        &config("analog = 3\ndigital = 70\nbits = 12\n"),
        Arc::new(MonotonicClock),
    )
    .unwrap();
    // The stimuli drive the outputs and run one bus cycle: the inputs follow.
    let mut set_ai = |c: u32, raw: i64| {
        card.write_raw(c, raw).unwrap();
        card.cycle();
    };
    conformance::check_analog_in(&*card, Some(&mut set_ai)).assert_complete();
    conformance::check_analog_out(&*card).assert_complete();
    let mut set_di = |b: u32, v: bool| {
        card.set_bit(b, v).unwrap();
        card.cycle();
    };
    conformance::check_digital_in(&*card, Some(&mut set_di)).assert_complete();
    conformance::check_digital_out(&*card).assert_complete();
}

fn errors(text: &str) -> String {
    let d = match Deployment::parse(text, "t.toml") {
        Ok(d) => d,
        Err(e) => return e.to_string(),
    };
    match Gateway::build(&d, "t.toml", text, &hwgw_example_driver::types()) {
        Ok(_) => "ok".into(),
        Err(p) => p
            .iter()
            .map(|p| p.to_string())
            .collect::<Vec<_>>()
            .join("\n"),
    }
}

#[test]
fn its_section_is_checked_like_any_driver_s() {
    let card = "[[card]]\nname = \"loop\"\ndriver = \"loopback\"\n[card.loopback]\n";
    assert_eq!(errors(&std::fs::read_to_string(DEPLOYMENT).unwrap()), "ok");
    assert_eq!(
        errors(&format!("{card}chanels = 3\n")),
        "t.toml:5:1: card[0].loopback.chanels: unknown field `chanels`, expected one of `analog`, `digital`, `lowest`, `highest`, `unit`, `bits`"
    );
    assert_eq!(
        errors(&format!("{card}analog = 100000\n")),
        "t.toml:5:10: card[0].loopback.analog: card \"loop\": 100000 channels: at most 1024"
    );
    assert_eq!(
        errors(&format!("{card}bits = \"many\"\n")),
        "t.toml:5:8: card[0].loopback.bits: invalid type: string \"many\", expected u32"
    );
    assert_eq!(
        errors("[[card]]\nname = \"loop\"\ndriver = \"loopback\"\n"),
        "t.toml:1:1: card[0]: card \"loop\" uses driver \"loopback\" but has no [card.loopback] section"
    );
    assert_eq!(
        errors("[[card]]\nname = \"x\"\ndriver = \"lopback\"\n"),
        "t.toml:3:10: card[0].driver: unknown driver \"lopback\"; this build has: canopen, comedi, firmata, gpio, i2c, loopback, modbus, sim, socketcan"
    );
}

#[test]
fn it_runs_in_hwgw_read_and_written_over_the_socket() {
    let svc = Service::start(BIN, "loopback", &[DEPLOYMENT], &[]).unwrap();
    // hwgw's own CLI, from the user's binary.
    svc.out(&["set", "loop.ao", "setpoint", "2500"]).unwrap();
    wait_until("the input follows the output", || {
        svc.out(&["get", "loop.ai", "feedback"]).ok().as_deref() == Some("2500.0")
    });
    svc.out(&["set", "loop.do", "bit3", "true"]).unwrap();
    wait_until("the digital input follows", || {
        svc.out(&["get", "loop.di", "bit3"]).ok().as_deref() == Some("true")
    });
    // An output port reads the device back.
    assert_eq!(svc.out(&["get", "loop.ao", "setpoint"]).unwrap(), "2500.0");
    let status = svc.ok(serde_json::json!({"cmd": "status"}));
    let card = &status["cards"][0];
    assert_eq!(
        (card["name"].as_str(), card["driver"].as_str()),
        (Some("loop"), Some("loopback"))
    );
    assert!(card["counters"]["cycles"].as_u64().unwrap() > 0, "{card}");
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(
        stopped
            .log
            .contains("card \"loop\" outputs at stop: analog [0, 0], digital on [7]"),
        "{}",
        stopped.log
    );
}

#[test]
fn the_device_outputs_are_what_the_gateway_drives() {
    let text = std::fs::read_to_string(DEPLOYMENT).unwrap();
    let d = Deployment::parse(&text, "loopback.toml").unwrap();
    let gw = Gateway::build(&d, "loopback.toml", &text, &hwgw_example_driver::types()).unwrap();
    assert!(
        gw.summary().contains(
            "card \"loop\" (loopback 2 analog and 8 digital channels looped back every 5ms)"
        ),
        "{}",
        gw.summary()
    );
    gw.start().unwrap();
    let ao = gw.runtime().registry().analog_out().lookup("loop").unwrap();
    ao.write(1, 4000.0).unwrap();
    let dout = gw
        .runtime()
        .registry()
        .digital_out()
        .lookup("loop")
        .unwrap();
    dout.set_bit(0, true).unwrap();
    let lines = gw.shutdown();
    assert_eq!(
        lines,
        vec!["card \"loop\" outputs at stop: analog [0, 0], digital on [7]"]
    );
}
