//! The GPIO card against the real kernel: gpio-sim chips in the kernel rig (the
//! character device's uAPI v2 on the Debian kernel), driven from outside through the
//! simulator's `pull` attribute, read back through its `value`, and libgpiod's tools
//! (`gpioinfo`, `gpioset`) as the independent peer. Each trial makes its own chip.
#![allow(clippy::unwrap_used, reason = "test code")]

use device_interface::conformance;
use device_interface::time::{Clock, MonotonicClock};
use device_interface::{Device, DeviceError, DigitalIn, DigitalOut, Status};
use driver_gpio::bus::{GpioBus, GpioEdge};
use driver_gpio::card::GpioCard;
use driver_gpio::component::GpioIo;
use driver_gpio::config::GpioConfig;
use kernel_rig::{Failed, Rig, Trial, sh};
use rtt::port::ConnPolicy;
use rtt::{Runtime, RuntimeOptions, TaskContext};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;
use testkit::gpiosim::check_pulses;
use testkit::{GpioTrace, SimChip, wait_for};

mod common;
use common::{card, running};

const PATIENCE: Duration = Duration::from_secs(10);

/// A card built from `body` (with `chip = "<label>"` first), its bus component running.
struct Up {
    card: Arc<GpioCard>,
    task: TaskContext,
    _rt: Runtime,
}

fn start(card: Arc<GpioCard>) -> Result<Up, Failed> {
    let (rt, task) = running(&card)?;
    Ok(Up {
        card,
        task,
        _rt: rt,
    })
}

fn up(chip: &SimChip, body: &str) -> Result<Up, Failed> {
    start(card(chip, body)?)
}

fn wait(what: &str, f: impl FnMut() -> bool) -> Result<(), Failed> {
    wait_for(what, PATIENCE, f).map_err(Failed::from)
}

fn bit(d: &dyn DigitalIn, b: u32) -> bool {
    d.read_bit(b)
        .unwrap_or_else(|e| panic!("read_bit({b}): {e}"))
}

fn inputs_follow_bias_polarity_and_the_outside() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-in", 8, &[(0, "up"), (1, "down")])?;
    let up = up(
        &chip,
        r#"input = [
            { line = "up", bias = "pull-up" },
            { line = "down", bias = "pull-down" },
            { line = 2, bias = "pull-up", active_low = true },
            { line = 3, bias = "pull-down", edges = "none" },
            { line = 4, bias = "disabled" },
        ]"#,
    )?;
    let c = &*up.card;
    // The request's bias sets the simulated line's level.
    assert_eq!(
        (bit(c, 0), bit(c, 1), bit(c, 2), bit(c, 3)),
        (true, false, false, false)
    );
    // Driven from outside: events keep the state (bits 0-2), bit 3 is read from the chip.
    chip.pull(0, false)?;
    chip.pull(1, true)?;
    chip.pull(2, false)?;
    chip.pull(3, true)?;
    wait("inputs follow the outside", || {
        (bit(c, 0), bit(c, 1), bit(c, 2), bit(c, 3)) == (false, true, true, true)
    })?;
    chip.pull(4, true)?;
    wait("a line without bias follows its pull", || bit(c, 4))?;
    // libgpiod sees what was requested.
    let info = sh(&format!("gpioinfo {}", chip.chip_name))?;
    let line = |o: u32| {
        info.lines()
            .find(|l| l.trim_start().starts_with(&format!("line {o:>3}:")))
            .unwrap_or("")
            .to_string()
    };
    for (o, bias) in [(0, "pull-up"), (1, "pull-down"), (4, "bias-disabled")] {
        let l = line(o);
        assert!(
            l.contains("\"hwgw\"") && l.contains("input") && l.contains(bias),
            "gpioinfo line {o}: {l:?}\n{info}"
        );
    }
    assert!(line(2).contains("active-low"), "{info}");
    Ok(())
}

/// Every edge read from the port `edges` so far.
fn edges(reader: &mut dyn rtt::component::DynReader) -> Vec<GpioEdge> {
    let mut out = Vec::new();
    while let (rtt::port::FlowStatus::NewData, Some(v)) = reader.read() {
        out.push(serde_json::from_value(v).unwrap());
    }
    out
}

fn edges_reach_the_port_with_kernel_times_and_sequence() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-edges", 4, &[])?;
    let up = up(&chip, "input = [{ line = 1, bias = \"pull-down\" }]")?;
    let mut reader = up.task.port("edges")?.reader(ConnPolicy::buffer(256))?;
    let before = MonotonicClock.now().as_nanos();
    for _ in 0..10 {
        chip.pull(1, true)?;
        wait("rising", || bit(&*up.card, 0))?;
        chip.pull(1, false)?;
        wait("falling", || !bit(&*up.card, 0))?;
    }
    let after = MonotonicClock.now().as_nanos();
    let mut seen = Vec::new();
    wait("20 edges on the port", || {
        seen.extend(edges(&mut *reader));
        seen.len() >= 20
    })?;
    assert_eq!(seen.len(), 20, "{seen:?}");
    for (i, e) in seen.iter().enumerate() {
        assert_eq!(e.rising, i % 2 == 0, "edge {i}: {e:?}");
        assert_eq!((e.bit, e.offset), (0, 1));
        assert_eq!(e.line_seqno as usize, i + 1, "{e:?}");
        assert!(
            before <= e.kernel_ns && e.kernel_ns <= after,
            "{e:?} not in {before}..{after}"
        );
        if i > 0 {
            assert!(e.kernel_ns > seen[i - 1].kernel_ns && e.seqno == seen[i - 1].seqno + 1);
        }
    }
    let c = up.card.counters();
    assert_eq!((c.events, c.lost_events), (20, 0), "{c:?}");
    Ok(())
}

fn debounce_hides_a_pulse_shorter_than_its_period() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-debounce", 2, &[])?;
    let up = up(
        &chip,
        "input = [{ line = 0, bias = \"pull-down\", debounce_us = 200000 }]",
    )?;
    let mut reader = up.task.port("edges")?.reader(ConnPolicy::buffer(64))?;
    // A pulse of a few hundred µs, then one held until the card sees it.
    chip.pull(0, true)?;
    chip.pull(0, false)?;
    chip.pull(0, true)?;
    wait("the long pulse", || bit(&*up.card, 0))?;
    chip.pull(0, false)?;
    wait("its end", || !bit(&*up.card, 0))?;
    let seen = edges(&mut *reader);
    // Events come in order: had the short pulse been seen, its edges would come first.
    assert_eq!(
        seen.iter().map(|e| e.rising).collect::<Vec<_>>(),
        [true, false],
        "{seen:?}"
    );
    let held = seen[1].kernel_ns - seen[0].kernel_ns;
    assert!(
        held >= 150_000_000,
        "a debounced pulse is at least the period long: {held} ns"
    );
    Ok(())
}

fn outputs_start_at_their_initial_value_and_follow_writes() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-out", 8, &[(4, "lamp")])?;
    // Pulled the other way before the request: a request that drove the line to
    // its default first would show here as the wrong level.
    chip.pull(4, false)?;
    chip.pull(5, true)?;
    let card = card(
        &chip,
        r#"output = [
            { line = "lamp", initial = true },
            { line = 5, initial = false },
            { line = 6, active_low = true },
            { line = 7, drive = "open-drain", initial = true },
        ]"#,
    )?;
    // Built but not started: nothing requested, nothing written.
    assert!(matches!(card.set_bit(0, false), Err(DeviceError::Offline)));
    assert!(!chip.value(4)? && chip.value(5)?);
    let up = start(card)?;
    let c = &*up.card;
    assert!(chip.value(4)?, "the initial value, from the request on");
    assert!(!chip.value(5)?);
    assert!(chip.value(6)?, "active low: bit off is a high line");
    c.set_bit(0, false)?;
    assert!(!chip.value(4)?);
    c.set_bit(2, true)?;
    assert!(!chip.value(6)?);
    // One ioctl for the lines of one request.
    c.set_sequence(0, 2, 0b011)?;
    assert_eq!(
        (chip.value(4)?, chip.value(5)?, chip.value(6)?),
        (true, true, true)
    );
    assert_eq!(c.check_sequence(0, 2)?, 0b011);
    let info = sh(&format!("gpioinfo {}", chip.chip_name))?;
    let lamp = info.lines().find(|l| l.contains("\"lamp\"")).unwrap_or("");
    assert!(
        lamp.contains("\"hwgw\"") && lamp.contains("output"),
        "{info}"
    );
    assert!(info.lines().any(|l| l.contains("open-drain")), "{info}");
    Ok(())
}

fn outputs_are_driven_to_no_level_but_their_initial_one_at_the_request() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-glitch", 4, &[])?;
    // Each line pulled to the level opposite to the one it is to start at.
    chip.pull(0, false)?;
    chip.pull(1, true)?;
    chip.pull(2, true)?;
    let card = card(
        &chip,
        r#"output = [
            { line = 0, initial = true },
            { line = 1, initial = false },
            { line = 2, active_low = true, initial = true },
        ]"#,
    )?;
    let base = chip.base()?;
    let trace = GpioTrace::start()?;
    let up = start(card)?;
    // The kernel's record: each line set once, to its initial level, then made an output.
    for (line, level) in [(0, "set 1"), (1, "set 0"), (2, "set 0")] {
        assert_eq!(
            trace.driven(base + line)?,
            [level, "out (0)"],
            "line {line}: driven before or besides its initial level"
        );
    }
    up.card.set_bit(1, true)?;
    assert_eq!(trace.driven(base + 1)?, ["set 0", "out (0)", "set 1"]);
    assert_eq!(trace.driven(base)?, ["set 1", "out (0)"], "written unasked");
    Ok(())
}

fn a_chip_that_goes_away_is_found_again() -> Result<(), Failed> {
    let mut chip = SimChip::new("hwgw-plug", 4, &[(0, "plug-in"), (1, "plug-out")])?;
    let up = up(
        &chip,
        r#"input = [{ line = "plug-in", bias = "pull-up" }]
           output = [{ line = "plug-out", initial = false }]"#,
    )?;
    let c = up.card.clone();
    let mut reader = up.task.port("edges")?.reader(ConnPolicy::buffer(64))?;
    c.set_bit(0, true)?;
    assert!(chip.value(1)? && bit(&*c, 0));
    // Held open here, the old chip keeps its number: the one that comes back gets another.
    let old = std::fs::File::open(chip.path())?;
    let old_name = chip.chip_name.clone();
    chip.unplug()?;
    wait("the card offline", || !c.counters().online)?;
    assert_eq!(c.counters().chips_lost, 1);
    assert!(matches!(c.set_bit(0, false), Err(DeviceError::Offline)));
    assert!(matches!(c.read_bit(0), Err(DeviceError::Offline)));
    assert_eq!(c.health().status, Status::Offline);
    let trace = GpioTrace::start()?;
    chip.plug()?;
    assert_ne!(
        chip.chip_name, old_name,
        "the chip came back under its old number"
    );
    wait("the card online again", || c.counters().online)?;
    drop(old);
    assert_eq!(c.counters().chips_back, 1);
    assert_eq!(c.health().status, Status::Online);
    // Requested again: the output driven to nothing but the level last written (a write
    // refused while offline changes nothing), the input's bias applied again (the
    // simulator's own default pull is down).
    assert_eq!(
        trace.driven(chip.base()? + 1)?,
        ["set 1", "out (0)"],
        "the output at re-request"
    );
    assert!(chip.value(1)?);
    assert!(bit(&*c, 0), "the pull-up applied again");
    chip.pull(0, false)?;
    wait("the input follows on the new chip", || !bit(&*c, 0))?;
    c.set_bit(0, false)?;
    assert!(!chip.value(1)?);
    let mut seen = Vec::new();
    wait("the edge on the port", || {
        seen.extend(edges(&mut *reader));
        !seen.is_empty()
    })?;
    assert!(
        seen.len() == 1 && !seen[0].rising && seen[0].line_seqno == 1,
        "{seen:?}"
    );
    assert_eq!(c.counters().lost_events, 0);
    let info = sh(&format!("gpioinfo {}", chip.chip_name))?;
    assert!(
        info.lines()
            .any(|l| l.contains("\"plug-out\"") && l.contains("\"hwgw\"") && l.contains("output")),
        "{info}"
    );
    // Again, nothing holding the old chip: back at its old number or another, found.
    chip.unplug()?;
    wait("offline a second time", || !c.counters().online)?;
    chip.plug()?;
    wait("online a second time", || c.counters().online)?;
    assert_eq!((c.counters().chips_lost, c.counters().chips_back), (2, 2));
    assert!(!chip.value(1)? && bit(&*c, 0));
    // Gone and back while the bus component is stopped (its requests kept, nothing
    // watching them): the start finds the stale request and the chip again.
    c.set_bit(0, true)?;
    up.task.stop()?;
    chip.unplug()?;
    chip.plug()?;
    up.task.start()?;
    assert!(c.counters().online && c.counters().chips_lost == 3);
    assert!(chip.value(1)? && bit(&*c, 0));
    Ok(())
}

/// A component that does nothing but step.
struct Idle;

impl rtt::Component for Idle {}

fn thread_scope_pulses_one_line_per_runtime_thread() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-scope", 4, &[])?;
    let card = card(
        &chip,
        "output = [{ line = 0 }, { line = 1 }, { line = 2 }, { line = 3 }]",
    )?;
    let registry = Arc::new(device_interface::Registry::new());
    registry.register_card("scope", card.devices())?;
    registry.alias(
        device_interface::Interface::DigitalOut,
        "ThreadScope",
        "scope",
    )?;
    let base = chip.base()?;
    let trace = GpioTrace::start()?;
    let rt = Runtime::new(
        registry,
        RuntimeOptions {
            thread_scope: true,
            ..RuntimeOptions::default()
        },
    )?;
    // Thread 1: the card's own bus component; threads 2 and 3: two periodic components.
    let io = GpioIo::add(&rt, "gpio", GpioBus::new(card.clone()), Default::default())?;
    io.start()?;
    let mut tasks = Vec::new();
    for (name, ms) in [("fast", 1), ("slow", 3)] {
        let t = rt.add(
            name,
            rtt::ActivitySpec::periodic(Duration::from_millis(ms)),
            rtt::InitialState::Stopped,
            |_| Ok(Idle),
        )?;
        t.start()?;
        tasks.push(t);
    }
    let pulses = |line: u32| trace.pulses(base + line);
    wait("20 pulses of each periodic thread", || {
        [2, 3]
            .iter()
            .all(|&l| pulses(l).is_ok_and(|p| p.len() >= 40))
    })?;
    for t in &tasks {
        t.stop()?;
    }
    for line in [2, 3] {
        // High while the thread steps, low between: strictly alternating, low at the end.
        check_pulses(&pulses(line)?).map_err(|e| format!("line {line}: {e}"))?;
    }
    assert_eq!(rt.thread_scope().errors(), 0);
    Ok(())
}

fn a_line_held_by_gpioset_is_refused_naming_it() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-busy", 4, &[(2, "taken")])?;
    let mut gpioset = std::process::Command::new("gpioset")
        .args(["--mode=signal", &chip.chip_name, "2=1"])
        .spawn()?;
    let held = || {
        sh(&format!("gpioinfo {}", chip.chip_name)).is_ok_and(|i| {
            i.lines()
                .any(|l| l.contains("\"taken\"") && l.contains("\"gpioset\""))
        })
    };
    let result = (|| {
        wait("gpioset holds the line", held)?;
        let config: GpioConfig = toml::from_str(&format!(
            "chip = {:?}\noutput = [{{ line = \"taken\" }}]",
            chip.label
        ))?;
        let e = driver_gpio::plugin::card(&config, Arc::new(MonotonicClock)).err();
        let e = e.ok_or("a held line was accepted")?;
        assert_eq!(e.key.as_deref(), Some("output[0].line"));
        assert!(
            e.message.contains("is used by \"gpioset\"") && e.message.contains("\"taken\""),
            "{}",
            e.message
        );
        Ok::<(), Failed>(())
    })();
    let _ = gpioset.kill();
    let _ = gpioset.wait();
    result?;
    // Taken between build and start: the start fails, naming the holder.
    let card = card(&chip, "input = [{ line = 2 }]")?;
    let mut gpioset = std::process::Command::new("gpioset")
        .args(["--mode=signal", &chip.chip_name, "2=1"])
        .spawn()?;
    let result = (|| {
        wait("gpioset holds the line again", held)?;
        let e = start(card).err().ok_or("started on a held line")?;
        let text = e.message().unwrap_or_default();
        assert!(text.contains("used by \"gpioset\""), "{text}");
        Ok::<(), Failed>(())
    })();
    let _ = gpioset.kill();
    let _ = gpioset.wait();
    result
}

fn an_encoder_decodes_ten_thousand_edges_exactly() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-enc", 4, &[(0, "encA"), (1, "encB"), (2, "encZ")])?;
    let up = up(
        &chip,
        "event_buffer = 1024\nencoder = [{ a = \"encA\", b = \"encB\", resolution = 1000 }]",
    )?;
    let enc = up.card.devices().encoders.remove(0).1;
    let mut q = chip.quadrature(0, 1)?;
    // In bursts the kernel's event buffer holds, each decoded before the next: the edges
    // are made far faster than an encoder turns, and on a loaded machine a reader that
    // fell behind a 10 000-edge burst would find the buffer overflowed (lost events).
    let counts = || Some(enc.turn().ok()? * 1000 + enc.position().ok()?);
    let mut at = 0i64;
    for burst in std::iter::repeat_n(500i64, 20).chain(std::iter::repeat_n(-500, 5)) {
        q.step(burst)?;
        at += burst;
        wait(&format!("{at} counts"), || counts() == Some(at))?;
    }
    assert_eq!((enc.turn().ok(), enc.position().ok()), (Some(7), Some(500)));
    let c = up.card.counters();
    assert_eq!(
        (c.events, c.lost_events, c.encoder_errors),
        (12_500, 0, 0),
        "{c:?}"
    );
    Ok(())
}

fn the_conformance_kit_passes() -> Result<(), Failed> {
    let chip = SimChip::new("hwgw-kit", 8, &[])?;
    let up = up(
        &chip,
        // Offsets out of order across roles: bits address lines by their place in the
        // request, whatever order the section gives them in. The kit moves the encoder in
        // bursts: a kernel buffer deep enough for a burst, so a reader delayed on a loaded
        // machine loses no edge (with the default one a full run lost some under load).
        r#"event_buffer = 1024
           input = [{ line = 6 }, { line = 4 }, { line = 5, edges = "none" }]
           output = [{ line = 3 }, { line = 0 }]
           encoder = [{ a = 2, b = 1, resolution = 400 }]"#,
    )?;
    let c = up.card.clone();
    let mut set_di = |b: u32, v: bool| {
        chip.pull([6, 4, 5][b as usize], v).unwrap();
        wait_for("the input follows", PATIENCE, || {
            c.read_bit(b).ok() == Some(v)
        })
        .unwrap();
    };
    conformance::check_digital_in(&*up.card, Some(&mut set_di)).assert_complete();
    conformance::check_digital_out(&*up.card).assert_complete();
    up.card.set_sequence(0, 1, 0b10)?;
    assert_eq!((chip.value(3)?, chip.value(0)?), (false, true));
    let enc = up.card.devices().encoders.remove(0).1;
    let mut q = chip.quadrature(2, 1)?;
    let e2 = enc.clone();
    let mut motion = |counts: i64| {
        let before = (e2.position().unwrap(), e2.turn().unwrap());
        let total = before.1 * 400 + before.0 + counts;
        q.step(counts).unwrap();
        wait_for("the encoder follows", PATIENCE, || {
            e2.position().unwrap() + e2.turn().unwrap() * 400 == total
        })
        .unwrap();
    };
    conformance::check_encoder(&*enc, Some(&mut motion)).assert_complete();
    Ok(())
}

fn main() -> ExitCode {
    let rig = Rig::new().gpio_sim();
    let trials = vec![
        Trial::test(
            "inputs_follow_bias_polarity_and_the_outside",
            inputs_follow_bias_polarity_and_the_outside,
        ),
        Trial::test(
            "edges_reach_the_port_with_kernel_times_and_sequence",
            edges_reach_the_port_with_kernel_times_and_sequence,
        ),
        Trial::test(
            "debounce_hides_a_pulse_shorter_than_its_period",
            debounce_hides_a_pulse_shorter_than_its_period,
        ),
        Trial::test(
            "outputs_start_at_their_initial_value_and_follow_writes",
            outputs_start_at_their_initial_value_and_follow_writes,
        ),
        Trial::test(
            "outputs_are_driven_to_no_level_but_their_initial_one_at_the_request",
            outputs_are_driven_to_no_level_but_their_initial_one_at_the_request,
        ),
        Trial::test(
            "a_chip_that_goes_away_is_found_again",
            a_chip_that_goes_away_is_found_again,
        ),
        Trial::test(
            "thread_scope_pulses_one_line_per_runtime_thread",
            thread_scope_pulses_one_line_per_runtime_thread,
        ),
        Trial::test(
            "a_line_held_by_gpioset_is_refused_naming_it",
            a_line_held_by_gpioset_is_refused_naming_it,
        ),
        Trial::test(
            "an_encoder_decodes_ten_thousand_edges_exactly",
            an_encoder_decodes_ten_thousand_edges_exactly,
        ),
        Trial::test("the_conformance_kit_passes", the_conformance_kit_passes),
    ];
    kernel_rig::harness(&rig, trials)
}
