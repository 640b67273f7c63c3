//! `hwgw` with a GPIO card, in the kernel rig: the real binary on `config/gpio.toml` over a
//! gpio-sim chip, inputs driven and outputs read through the simulator, libgpiod's
//! `gpioinfo` as the independent view of the lines, the CLI in between.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Rig, Trial, sh};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use testkit::gpiosim::check_pulses;
use testkit::wait::wait_ok;
use testkit::{Service, SimChip};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/gpio.toml");

fn hwgw_gets_sets_and_leaves_the_lamp_safe() -> Result<(), Failed> {
    // The chip config/gpio.toml expects (its header says how to make it by hand).
    let chip = SimChip::new("hwgw-demo", 8, &[(0, "button"), (1, "limit"), (4, "lamp")])?;
    // The lamp's line is pulled up before hwgw requests it: requested at its initial value
    // (off) it must go low, and when hwgw exits and releases it, high again.
    chip.pull(4, true)?;
    let gw = Service::start(HWGW, "gpio", &[CONFIG], &[])?;
    let get = |port: &str, name: &str| gw.out(&["get", port, name]).map_err(Failed::from);
    wait_ok("the card online", || {
        Ok(gw
            .out(&["call", "gpio", "counters"])?
            .contains("\"online\": true"))
    })?;
    assert!(
        !chip.value(4)?,
        "the lamp at its initial value (off) from the request on"
    );

    // Inputs: the button (pull-down), the limit switch (pull-up, active low).
    assert_eq!(get("gpio.di", "button")?, "false");
    assert_eq!(get("gpio.di", "limit")?, "false");
    chip.pull(0, true)?;
    chip.pull(1, false)?;
    wait_ok("button and limit on", || {
        Ok(get("gpio.di", "button")? == "true" && get("gpio.di", "limit")? == "true")
    })?;

    // Outputs: hwgw set, read back through the simulator.
    gw.out(&["set", "gpio.do", "lamp", "true"])?;
    if let Err(e) = wait_ok("the lamp on", || Ok(chip.value(4)?)) {
        let lamp = gw.out(&["get", "gpio.do", "lamp"]);
        let counters = gw.out(&["call", "gpio", "counters"]);
        let stopped = gw.terminate();
        return Err(format!(
            "{e:?}: lamp {lamp:?}, counters {counters:?}, log:\n{}",
            stopped.log
        )
        .into());
    }
    let info = sh(&format!("gpioinfo {}", chip.chip_name))?;
    for name in ["\"button\"", "\"limit\"", "\"lamp\""] {
        let line = info.lines().find(|l| l.contains(name)).unwrap_or("");
        assert!(line.contains("\"hwgw\""), "{name}: {line:?}\n{info}");
    }
    // The encoder on lines 2 and 3: one cycle forward is 4 counts.
    for (line, level) in [(2, true), (3, true), (2, false), (3, false)] {
        chip.pull(line, level)?;
    }
    wait_ok("4 counts", || {
        Ok(gw.out(&["get", "gpio.encoder0", "position"])? == "4")
    })?;
    let status = gw.out(&["status"])?;
    assert!(status.contains(&chip.chip_name), "{status}");

    // SIGTERM: the lamp goes to its safe value (off, low) while hwgw still holds the line,
    // then back to the pull (high) once hwgw has exited and the kernel released it.
    let watching = Arc::new(AtomicBool::new(true));
    let seen_low = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (watching, seen_low) = (watching.clone(), seen_low.clone());
        let value = chip.value(4)?;
        assert!(value);
        let path = format!(
            "/sys/devices/platform/{}/{}/sim_gpio4/value",
            chip.dev_name, chip.chip_name
        );
        std::thread::spawn(move || {
            while watching.load(Ordering::Acquire) {
                if std::fs::read_to_string(&path).is_ok_and(|v| v.trim() == "0") {
                    seen_low.store(true, Ordering::Release);
                }
            }
        })
    };
    let stopped = gw.terminate();
    watching.store(false, Ordering::Release);
    let _ = sampler.join();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(stopped.log.contains("digital on []"), "{}", stopped.log);
    assert!(
        seen_low.load(Ordering::Acquire),
        "the lamp never went to its safe value (low)"
    );
    wait_ok("the line released to its pull", || Ok(chip.value(4)?))?;
    Ok(())
}

/// Each input case of the section, read by `hwgw get`: every bias, active low on a line
/// with edge events and on one read by ioctl, and a debounced line a short pulse does not
/// reach.
const INPUTS: &str = r#"
[[card]]
name = "gpio"
driver = "gpio"
sample_period_ms = 5

[card.names]
digital_in = ["up", "down", "floating", "low_active", "debounced", "polled"]

[card.gpio]
chip = "hwgw-cases"

[[card.gpio.input]]
line = 0
bias = "pull-up"

[[card.gpio.input]]
line = 1
bias = "pull-down"

[[card.gpio.input]]
line = 2
bias = "disabled"

[[card.gpio.input]]
line = 3
bias = "pull-up"
active_low = true

[[card.gpio.input]]
line = 4
bias = "pull-down"
debounce_us = 200000

[[card.gpio.input]]
line = 5
bias = "pull-down"
active_low = true
edges = "none"
"#;

fn hwgw_get_reads_each_bias_polarity_and_debounce_case() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-cases", 8, &[])?;
    let dir = testkit::TempDir::new("gpio-cases-config");
    let config = dir.path().join("cases.toml");
    std::fs::write(&config, INPUTS)?;
    let gw = Service::start(HWGW, "gpio-cases", &[&config], &[])?;
    let get = |name: &str| gw.out(&["get", "gpio.di", name]).map_err(Failed::from);
    let all = || -> Result<Vec<String>, Failed> {
        [
            "up",
            "down",
            "floating",
            "low_active",
            "debounced",
            "polled",
        ]
        .iter()
        .map(|n| get(n))
        .collect()
    };
    wait_ok("the card online", || {
        Ok(gw
            .out(&["call", "gpio", "counters"])?
            .contains("\"online\": true"))
    })?;
    // As requested: the bias sets the simulated line, active low inverts it (a line
    // without bias stays where the simulator's default pull has it: low).
    wait_ok("the levels the biases give", || {
        Ok(all()? == ["true", "false", "false", "false", "false", "true"])
    })?;
    let info = sh(&format!("gpioinfo {}", chip.chip_name))?;
    for (line, words) in [
        (0, &["pull-up"][..]),
        (1, &["pull-down"]),
        (2, &["bias-disabled"]),
        (3, &["pull-up", "active-low"]),
        // Debian's gpioinfo (libgpiod 1.6) does not print debounce periods: the pulses
        // below show this one.
        (4, &["pull-down"]),
        (5, &["pull-down", "active-low"]),
    ] {
        let l = info
            .lines()
            .find(|l| l.trim_start().starts_with(&format!("line {line:>3}:")))
            .unwrap_or("");
        for w in words {
            assert!(
                l.contains(w) && l.contains("\"hwgw\""),
                "line {line}: {w}: {l:?}\n{info}"
            );
        }
    }
    // Driven from outside, each the other way.
    chip.pull(0, false)?;
    chip.pull(1, true)?;
    chip.pull(2, true)?;
    chip.pull(3, false)?;
    chip.pull(5, true)?;
    wait_ok("every case the other way", || {
        Ok(all()? == ["false", "true", "true", "true", "false", "false"])
    })?;
    // A pulse far shorter than the 200 ms debounce period, then one held until seen.
    chip.pull(4, true)?;
    chip.pull(4, false)?;
    chip.pull(4, true)?;
    wait_ok("the held pulse", || Ok(get("debounced")? == "true"))?;
    chip.pull(4, false)?;
    wait_ok("its end", || Ok(get("debounced")? == "false"))?;
    // The kernel's events: one edge on each of lines 0-3, two on line 4 (the short
    // pulse never reached the card), none on line 5 (no edge detection).
    let counters = gw.out(&["call", "gpio", "counters"])?;
    assert!(
        counters.contains("\"events\": 6,") && counters.contains("\"lost_events\": 0,"),
        "{counters}"
    );
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    Ok(())
}

/// ThreadScope on a GPIO card, as `config/gpio.toml`'s commented block sets it up, with
/// a simulated card whose bus cycle and sampling step every 2 ms on threads of their own
/// (the GPIO card's own threads step only when asked: it has no inputs).
const SCOPE: &str = r#"
thread_scope = true

[[card]]
name = "sim0"
driver = "sim"
period_ms = 2
sample_period_ms = 2

[card.sim]
digital_inputs = 2

[[card]]
name = "scope"
driver = "gpio"
sample_period_ms = 2

[card.gpio]
chip = "hwgw-scope"
output = [{ line = 0 }, { line = 1 }, { line = 2 }, { line = 3 }, { line = 4 }, { line = 5 }, { line = 6 }, { line = 7 }]

[[alias]]
interface = "digital_out"
name = "ThreadScope"
target = "scope"
"#;

fn hwgw_pulses_thread_scope_on_gpio_lines() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-scope", 8, &[])?;
    let base = chip.base()?;
    let dir = testkit::TempDir::new("gpio-scope-config");
    let config = dir.path().join("scope.toml");
    std::fs::write(&config, SCOPE)?;
    let trace = testkit::GpioTrace::start()?;
    let gw = Service::start(HWGW, "gpio-scope", &[&config], &[])?;
    // Pulses after the request's "set 0", "out (0)", per line.
    let pulses = |line: u32| trace.pulses(base + line);
    let waited = wait_ok("a thread pulsing its line 20 times", || {
        Ok((1..8).any(|l| pulses(l).is_ok_and(|p| p.len() >= 40)))
    });
    if let Err(e) = waited {
        let seen: Vec<_> = (0..8).map(|l| trace.driven(base + l)).collect();
        let status = gw.out(&["status"]);
        let stopped = gw.terminate();
        return Err(format!(
            "{e:?}: events {seen:?}\nstatus {status:?}\nlog:\n{}",
            stopped.log
        )
        .into());
    }
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(stopped.log.contains("ThreadScope"), "{}", stopped.log);
    let mut busy = 0;
    for line in 0..8 {
        let p = pulses(line)?;
        busy += usize::from(p.len() >= 2);
        check_pulses(&p).map_err(|e| format!("line {line}: {e}"))?;
    }
    assert!(
        busy >= 2,
        "pulses on {busy} lines: one thread each expected"
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    kernel_rig::harness(
        &Rig::new().gpio_sim(),
        vec![
            Trial::test(
                "hwgw_gets_sets_and_leaves_the_lamp_safe",
                hwgw_gets_sets_and_leaves_the_lamp_safe,
            ),
            Trial::test(
                "hwgw_get_reads_each_bias_polarity_and_debounce_case",
                hwgw_get_reads_each_bias_polarity_and_debounce_case,
            ),
            Trial::test(
                "hwgw_pulses_thread_scope_on_gpio_lines",
                hwgw_pulses_thread_scope_on_gpio_lines,
            ),
        ],
    )
}
