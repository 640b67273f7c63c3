//! Logical devices with the real binary on `config/axis.toml`: the axis homed on the
//! simulated card through `hwgw call`, its latch at the home switch's edge, a limit switch
//! (tripped through the card's digital loopback) disabling the drive and putting the axis
//! in error, recovery away from the limit, and the drive disabled with its setpoint at its
//! safe value when the gateway stops.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::Value;
use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const AXIS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/axis.toml");

fn status(svc: &Service) -> Value {
    serde_json::from_str(&svc.out(&["call", "axis0", "status"]).unwrap()).unwrap()
}

fn number(svc: &Service, args: &[&str]) -> f64 {
    let text = svc.out(args).unwrap_or_else(|e| panic!("{e}"));
    text.parse()
        .unwrap_or_else(|e| panic!("{args:?} gave {text:?}: {e}"))
}

/// `hwgw call …` refused with `message` in its error.
fn refused(svc: &Service, args: &[&str], message: &str) {
    let e = svc.out(args).unwrap_err();
    assert!(e.contains(message), "{args:?}: {e}");
}

#[test]
fn the_axis_homes_stops_at_a_limit_and_leaves_the_drive_disabled_at_stop() {
    let svc = Service::start(HWGW, "axis", &[AXIS], &[]).unwrap_or_else(|e| panic!("{e}"));
    let ok = |args: &[&str]| svc.out(args).unwrap_or_else(|e| panic!("{e}"));
    wait_until("the axis component running", || {
        ok(&["ls", "axis0"]).starts_with("axis0 [running]")
    });
    assert_eq!(status(&svc)["state"], "disabled");
    refused(
        &svc,
        &["call", "axis0", "home"],
        "homing starts from an enabled axis",
    );

    ok(&["call", "axis0", "enable"]);
    assert_eq!(ok(&["call", "drive0", "enabled"]), "true");
    ok(&["call", "axis0", "home"]);
    assert_eq!(status(&svc)["state"], "homing");
    wait_until("homing to end", || status(&svc)["state"] != "homing");
    let s = status(&svc);
    assert_eq!(s["state"], "ready", "{s}");
    assert_eq!(s["homed"], true);
    // Backed off 2 mm from the edge (position 0), within the motion of a few cycles.
    let p = s["position"].as_f64().unwrap();
    assert!((p + 2.0).abs() < 1.0, "homed at {p} mm");
    // The latch is at the switch's edge, 5000 counts (50 mm) of travel: the encoder's count
    // (homing did not set it) less the axis' position. The count is sampled every 5 ms;
    // standing still, it stays.
    let latch = || {
        let pos = number(&svc, &["get", "sim0.encoder0", "position"]);
        let turn = number(&svc, &["get", "sim0.encoder0", "turn"]);
        let axis = number(&svc, &["call", "axis0", "position"]);
        (turn * 4096.0 + pos) / 100.0 - axis
    };
    let mut seen = latch();
    wait_until("the encoder's sample to settle after the back-off", || {
        let now = latch();
        std::mem::replace(&mut seen, now) == now
    });
    // At most 250 ms of motion at the search velocity late (a loaded machine's steps).
    eprintln!("latched at {seen} mm of travel; the switch's edge is at 50 mm");
    assert!(
        (50.0..55.0).contains(&seen),
        "latched at {seen} mm of travel"
    );

    // The high limit switch while moving up: the drive disabled, the axis in error.
    ok(&["call", "axis0", "jog", "5"]);
    ok(&["call", "sim0.do", "set_bit", "6", "true"]);
    wait_until("the limit to stop the axis", || {
        status(&svc)["state"] == "error"
    });
    let s = status(&svc);
    assert_eq!(s["fault"], "the high limit switch turned on", "{s}");
    assert_eq!(ok(&["call", "drive0", "enabled"]), "false");
    assert_eq!(ok(&["get", "sim0.do", "bit0"]), "false");
    assert!(number(&svc, &["get", "sim0.ao", "ch1"]).abs() < 1e-3);
    refused(&svc, &["call", "axis0", "jog", "-5"], "reset it first");

    // Reset, enable: away from the limit only.
    ok(&["call", "axis0", "reset"]);
    ok(&["call", "axis0", "enable"]);
    refused(
        &svc,
        &["call", "axis0", "jog", "5"],
        "the high limit switch is on",
    );
    ok(&["call", "axis0", "jog", "-5"]);
    assert_eq!(status(&svc)["state"], "moving");
    ok(&["call", "sim0.do", "set_bit", "6", "false"]);

    // Stopped while moving: the card's outputs are held first (no racing write), then its
    // policy — which `hwgw check` requires of a drive's outputs — drives the enable off and
    // the setpoint to the safe 0 V (the nearest step of a 16-bit output over ±10 V).
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(
        stopped.log.contains(
            "card \"sim0\" outputs at stop: analog [0.00015259021896696368, 0.00015259021896696368], digital on []"
        ),
        "{}",
        stopped.log
    );
}

/// A gateway of `text` built in this process, started.
fn started(text: &str) -> hwgw::deploy::Gateway {
    let (gw, _) =
        hwgw::deploy::Gateway::from_text(text, "axis.toml", &hwgw::types::Types::builtin())
            .unwrap_or_else(|e| panic!("{e}"));
    gw.start().unwrap();
    gw
}

#[test]
fn a_reload_leaves_logical_devices_and_their_cards_as_they_run() {
    let text = std::fs::read_to_string(AXIS).unwrap();
    let gw = started(&text);
    let axis = gw.runtime().registry().axis().lookup("axis0").unwrap();
    let drive = gw.runtime().registry().drive().lookup("drive0").unwrap();
    axis.enable().unwrap();

    // The axis changed: named as needing a restart, the running one untouched.
    let changed = text.replace("back_off = 2.0", "back_off = 3.0");
    let report = gw.reload_text(&changed, "axis.toml");
    assert!(report.errors.is_empty(), "{report:?}");
    assert_eq!(
        report.restart,
        ["[[logical]] changed: restart hwgw to apply"]
    );
    assert!(gw.runtime().registry().axis().lookup("axis0").is_ok());
    assert!(drive.is_enabled());

    // The card under it changed: kept as it runs, with the reason.
    let card = text.replacen("period_ms = 5 ", "period_ms = 4 ", 1);
    let report = gw.reload_text(&card, "axis.toml");
    assert!(report.errors.is_empty(), "{report:?}");
    assert_eq!(
        report.restart,
        [
            "card \"sim0\" changed, but the logical device \"drive0\" is built on it: restart hwgw to apply"
        ]
    );
    assert!(drive.is_enabled());
    let lines = gw.shutdown();
    // Moving, enabled at the stop: the card's policy drove the drive's outputs safe.
    assert_eq!(
        lines,
        [
            "card \"sim0\" outputs at stop: analog [0.00015259021896696368, 0.00015259021896696368], digital on []"
        ]
    );
}

#[test]
fn an_enabled_axis_keeps_its_drives_output_watchdog_fed() {
    let text = std::fs::read_to_string(AXIS).unwrap().replace(
        "safe = { ch1 = 0.0, bit0 = false }",
        "safe = { ch1 = 0.0, bit0 = false }\nwatchdog_ms = 250",
    );
    let gw = started(&text);
    let reg = gw.runtime().registry();
    let axis = reg.axis().lookup("axis0").unwrap();
    axis.enable().unwrap();
    axis.jog(1.0).unwrap();
    // Four watchdog periods (250 ms, a margin for a loaded machine): the axis rewrites its
    // outputs every 5 ms on its own thread.
    std::thread::sleep(std::time::Duration::from_millis(1000));
    let dout = reg.digital_out().lookup("sim0").unwrap();
    assert!(dout.check_bit(0).unwrap(), "the enable went off");
    assert_eq!(gw.card_status()[0].outputs.watchdog_trips, 0);
    assert_eq!(axis.state().to_string(), "moving");
    // Its component stopped: nothing writes them now, and the watchdog has them at their
    // safe values (the stop disabled the drive already).
    gw.runtime().component("axis0").unwrap().stop().unwrap();
    assert!(!dout.check_bit(0).unwrap());
    drop(gw.shutdown());
}
