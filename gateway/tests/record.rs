//! Recordings of the demo deployment by the real binary — `hwgw record`, a triggered
//! capture, the `recorder` component — read back by the independent `mcap` package from
//! PyPI, and drawn by `hwgw plot` (checked by pixel statistics).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::Value;
use std::path::Path;
use std::process::Command;
use testkit::mcapread::{Dump, Topic};
use testkit::picture::png_stats;
use testkit::{Service, TempDir, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const MS: u64 = 1_000_000;

fn median_gap(times: &[u64]) -> u64 {
    let mut gaps: Vec<u64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_unstable();
    gaps[gaps.len() / 2]
}

fn topic<'a>(d: &'a Dump, name: &str) -> &'a Topic {
    d.topics
        .get(name)
        .unwrap_or_else(|| panic!("{name} not in {:?}", d.topics.keys().collect::<Vec<_>>()))
}

/// Every message decodes with its channel's schema's shape: a port's `{"value"}`, an
/// activity's step times; JSON messages with JSON schemas.
fn check_shapes(d: &Dump) {
    let mut total = 0;
    for (name, t) in &d.topics {
        assert_eq!(t.encoding, "json", "{name}");
        assert_eq!(t.schema.1, "jsonschema", "{name}");
        assert!(
            t.times.windows(2).all(|w| w[0] <= w[1]),
            "{name}: times go back"
        );
        for m in &t.messages {
            if name.starts_with("/activity/") {
                let n = |k: &str| m[k].as_u64().unwrap_or_else(|| panic!("{name}: {m}"));
                assert!(n("scheduled_ns") <= n("started_ns") && n("started_ns") <= n("ended_ns"));
                let late = m["lateness_us"].as_f64().unwrap() * 1e3;
                assert!(
                    (late - (n("started_ns") - n("scheduled_ns")) as f64).abs() < 1.0,
                    "{m}"
                );
            } else {
                assert!(m.get("value").is_some(), "{name}: {m}");
            }
        }
        total += t.messages.len() as u64;
    }
    assert_eq!(d.message_count, total);
    assert_eq!(d.metadata["hwgw.recording"]["messages"], total.to_string());
}

fn plot(svc: &Service, rec: &Path, kind: &str, out: &Path) {
    let o = svc.out(&[
        "plot",
        rec.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--kind",
        kind,
    ]);
    o.unwrap();
    let s = png_stats(out).unwrap();
    assert_eq!((s.width, s.height), (1280, 720), "{kind}");
    assert!(s.drawn > 0.02 && s.drawn < 0.95, "{kind}: {s:?}");
    assert!(s.colours > 8, "{kind}: {s:?}");
}

/// 3 s of every device channel, follow, blink and every activity: counts and times match
/// the ports' sample periods and the activities' periods; nothing lost; the three kinds
/// of picture and the live histograms drawn.
#[test]
fn a_recording_of_the_demo_reads_back_with_the_mcap_package() {
    let svc = Service::start(HWGW, "record-demo", &[] as &[&str], &[]).unwrap();
    let file = svc.dir().join("demo.mcap");
    let f = file.to_str().unwrap();
    let said = svc
        .out(&[
            "record",
            f,
            "--devices",
            "--port",
            "follow",
            "--port",
            "blink",
            "--duration",
            "3s",
        ])
        .unwrap();
    assert!(
        said.contains(", 0 lost,") && said.contains("ended: duration"),
        "{said}"
    );
    let d = testkit::mcapread::read(&file).unwrap();
    check_shapes(&d);
    assert_eq!(d.metadata["hwgw.recording"]["lost"], "0");
    // sim0 samples its inputs every 20 ms: 3 s is 150 samples (one more at the edges; a
    // step skipped under load, fewer), one for each step of sim0.ai recorded.
    let ai_steps = topic(&d, "/activity/sim0.ai").times.len();
    for ch in ["/sim0/ai/ch0", "/sim0/ai/ch1", "/sim0/ai/ch3"] {
        let t = topic(&d, ch);
        assert!(
            (140..=152).contains(&t.times.len()) && t.times.len().abs_diff(ai_steps) <= 1,
            "{ch}: {} samples, {ai_steps} steps",
            t.times.len()
        );
        let gap = median_gap(&t.times);
        assert!(
            (19 * MS..=21 * MS).contains(&gap),
            "{ch}: median gap {gap} ns"
        );
        assert!(t.messages.iter().all(|m| m["value"].is_f64()), "{ch}");
    }
    // The ramp on ch1 rises 5 V/s: 20 ms apart is 0.1 V apart (the card's bus thread
    // samples every 10 ms, so a sample may be a bus cycle off its neighbours).
    let ramp: Vec<f64> = topic(&d, "/sim0/ai/ch1")
        .messages
        .iter()
        .map(|m| m["value"].as_f64().unwrap())
        .collect();
    let mut rises: Vec<f64> = ramp
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > -1.0)
        .collect();
    rises.sort_by(f64::total_cmp);
    assert!((rises[rises.len() / 2] - 0.1).abs() < 0.01, "{ramp:?}");
    let near = rises.iter().filter(|d| (**d - 0.1).abs() <= 0.06).count();
    assert!(near * 10 >= rises.len() * 9, "{ramp:?}");
    // blink toggles every 250 ms.
    let blink = topic(&d, "/blink/state");
    assert!(
        (11..=13).contains(&blink.times.len()),
        "{}",
        blink.times.len()
    );
    let gap = median_gap(&blink.times);
    assert!((245 * MS..=255 * MS).contains(&gap), "blink: {gap}");
    assert!(
        blink
            .messages
            .windows(2)
            .all(|w| w[0]["value"] != w[1]["value"])
    );
    // The card's bus thread steps every 10 ms on an absolute grid.
    let bus = topic(&d, "/activity/sim0");
    assert!(
        (280..=305).contains(&bus.times.len()),
        "{}",
        bus.times.len()
    );
    let due: Vec<u64> = bus
        .messages
        .iter()
        .map(|m| m["scheduled_ns"].as_u64().unwrap())
        .collect();
    assert_eq!(median_gap(&due), 10 * MS);
    assert!(d.topics.contains_key("/activity/follow") && d.topics.contains_key("/follow/out"));

    let pic = |n: &str| svc.dir().join(n);
    plot(&svc, &file, "values", &pic("values.png"));
    plot(&svc, &file, "timing", &pic("timing.png"));
    plot(&svc, &file, "lateness", &pic("lateness.png"));
    let live = pic("live.png");
    svc.out(&["status", "--plot", live.to_str().unwrap()])
        .unwrap();
    let s = png_stats(&live).unwrap();
    assert!(s.drawn > 0.02 && s.colours > 8, "{s:?}");
    // Nothing is overwritten.
    let again = svc.cli(&["record", f, "--port", "follow", "--duration", "1s"]);
    assert!(!again.status.success() && String::from_utf8_lossy(&again.stderr).contains("exists"));
    let again = svc.cli(&["plot", f, "-o", live.to_str().unwrap()]);
    assert!(!again.status.success() && String::from_utf8_lossy(&again.stderr).contains("exists"));
}

/// `--trigger 'sim0.ai.ch1 > 0' --pre 300ms --post 700ms`: every message lies within the
/// window; the window is exactly 1 s around the first ramp sample above 0; its edges hold
/// samples within one sample period.
#[test]
fn a_triggered_capture_holds_exactly_the_window_asked_for() {
    let svc = Service::start(HWGW, "record-trigger", &[] as &[&str], &[]).unwrap();
    let file = svc.dir().join("trig.mcap");
    let said = svc
        .out(&[
            "record",
            file.to_str().unwrap(),
            "--port",
            "sim0.ai.ch0",
            "--trigger",
            "sim0.ai.ch1 > 0",
            "--pre",
            "300ms",
            "--post",
            "700ms",
            "--duration",
            "10s",
        ])
        .unwrap();
    assert!(said.contains("the trigger window is complete"), "{said}");
    let d = testkit::mcapread::read(&file).unwrap();
    check_shapes(&d);
    let meta = &d.metadata["hwgw.recording"];
    let n = |k: &str| {
        meta[k]
            .parse::<u64>()
            .unwrap_or_else(|_| panic!("{k}: {meta:?}"))
    };
    let (at, start, end) = (
        n("trigger.at_ns"),
        n("trigger.window_start_ns"),
        n("trigger.window_end_ns"),
    );
    assert_eq!((at - start, end - at), (300 * MS, 700 * MS));
    assert_eq!(
        n("trigger.complete_from_ns"),
        start,
        "the ring let go of none of it"
    );
    assert_eq!(meta["trigger.ring_overflow"], "0");
    for (name, t) in &d.topics {
        assert!(
            t.times.iter().all(|x| (start..=end).contains(x)),
            "{name} outside the window"
        );
    }
    let ramp = topic(&d, "/sim0/ai/ch1");
    let i = ramp
        .times
        .iter()
        .position(|&t| t == at)
        .expect("the trigger sample is recorded");
    assert!(ramp.messages[i]["value"].as_f64().unwrap() > 0.0);
    assert!(
        i > 0 && ramp.messages[i - 1]["value"].as_f64().unwrap() <= 0.0,
        "not the edge"
    );
    // The samples are those of sim0.ai's steps in the window (a sample takes its step's
    // start): every step's, and at the edges none of a step that began within the window
    // is missing.
    let steps = topic(&d, "/activity/sim0.ai");
    let due: std::collections::BTreeMap<u64, u64> = steps
        .messages
        .iter()
        .zip(&steps.times)
        .map(|(m, &t)| {
            let n = |k: &str| m[k].as_u64().unwrap();
            (t, n("scheduled_ns") + t - n("started_ns"))
        })
        .collect();
    let late = steps
        .messages
        .iter()
        .map(|m| m["started_ns"].as_u64().unwrap() - m["scheduled_ns"].as_u64().unwrap())
        .max()
        .unwrap();
    for t in [ramp, topic(&d, "/sim0/ai/ch0")] {
        let grid: Vec<u64> = t.times.iter().map(|x| due[x]).collect();
        assert!(
            // A step skipped under load leaves a gap of whole periods, never part of one.
            grid.windows(2).all(|w| (w[1] - w[0]) % (20 * MS) == 0),
            "off the grid: {grid:?}"
        );
        assert!(
            grid[0] - 20 * MS < start,
            "the step before the first began after the start"
        );
        assert!(
            grid[grid.len() - 1] + 20 * MS + late + MS > end,
            "one missing at the end"
        );
        assert_eq!(t.times.len(), steps.times.len(), "a sample for each step");
    }
    assert!(
        d.topics.keys().any(|k| k.starts_with("/activity/")),
        "steps recorded too"
    );
}

/// The `recorder` component on the demo: `check` creates nothing; `run` records until
/// SIGTERM, and the file is complete and read back; a second `check` refuses the file.
#[test]
fn the_recorder_component_records_while_it_runs() {
    let dir = TempDir::new("record-component-files");
    let config = dir.path().join("demo.toml");
    let file = dir.path().join("rec.mcap");
    let text = format!(
        "{}\n[[component]]\nname = \"rec\"\ntype = \"recorder\"\nactivity = {{ type = \"periodic\", period_ms = 20 }}\n\
         properties = {{ ports = [\"sim0.ai\", \"follow.out\"], activities = [\"sim0.ai\"], file = {:?} }}\n",
        hwgw::DEMO,
        file.to_str().unwrap()
    );
    std::fs::write(&config, text).unwrap();
    let check = || testkit::service::check(HWGW, &config);
    let out = check();
    assert!(out.status.success(), "{out:?}");
    assert!(!file.exists(), "check created the recording");
    let svc = Service::start(HWGW, "record-component", &[&config], &[]).unwrap();
    wait_until("the recorder wrote 200 messages", || {
        svc.ok(serde_json::json!({"cmd": "get", "component": "rec", "port": "written"}))
            .as_u64()
            .is_some_and(|n| n >= 200)
    });
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(stopped.log.contains("rec.mcap finished"), "{}", stopped.log);
    let d = testkit::mcapread::read(&file).unwrap();
    check_shapes(&d);
    assert_eq!(d.metadata["hwgw.recording"]["lost"], "0");
    let ch0 = topic(&d, "/sim0/ai/ch0");
    assert!(ch0.times.len() >= 20, "{}", ch0.times.len());
    assert!((19 * MS..=21 * MS).contains(&median_gap(&ch0.times)));
    let steps = topic(&d, "/activity/sim0.ai");
    assert!(
        steps
            .messages
            .iter()
            .all(|m| m.get("lateness_us").is_some_and(Value::is_f64))
    );
    let out = check();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("exists"), "{err}");
}

/// `hwgw record` with no duration records until Ctrl-C (SIGINT), then completes the file:
/// it reads back with its metadata, ended by the signal.
#[test]
fn ctrl_c_ends_a_recording_with_a_complete_file() {
    use nix::sys::signal::{Signal, kill};
    use nix::unistd::Pid;
    let svc = Service::start(HWGW, "record-sigint", &[] as &[&str], &[]).unwrap();
    let file = svc.dir().join("open.mcap");
    let mut child = Command::new(HWGW)
        .args([
            "record",
            file.to_str().unwrap(),
            "--port",
            "sim0.ai",
            "--socket",
        ])
        .arg(&svc.socket)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The file is made once the gateway has the stream's connections in place; ten new
    // values of ch2 seen after that went into the recording's buffers too.
    wait_until("the recording file", || file.exists());
    svc.out(&["watch", "sim0.ai", "ch2", "--count", "10"])
        .unwrap();
    kill(Pid::from_raw(child.id() as i32), Signal::SIGINT).unwrap();
    let status = child.wait().unwrap();
    let mut said = String::new();
    std::io::Read::read_to_string(child.stdout.as_mut().unwrap(), &mut said).unwrap();
    assert!(status.success(), "{status:?}: {said}");
    assert!(said.contains("ended: stopped by a signal"), "{said}");
    let d = testkit::mcapread::read(&file).unwrap();
    check_shapes(&d);
    assert_eq!(d.metadata["hwgw.recording"]["ended"], "stopped by a signal");
    assert!(topic(&d, "/sim0/ai/ch2").times.len() >= 10);
}

/// `hwgw record` onto a disk that fills up — a 512 KiB tmpfs mounted in a mount namespace
/// of its own (`unshare -m`), where the demo's ~150 KB/s fill it in a few seconds: it
/// fails naming the full disk (ENOSPC) and the file, and the file — cut back to its last
/// complete chunk and completed there — reads back whole with the independent reader,
/// its messages in time order from the start, the failure in its metadata. Cut short of
/// its footer, `hwgw plot` says it is cut and after how many messages; a complete
/// recording that holds nothing is told apart ("no messages").
#[test]
fn a_recording_on_a_full_disk_names_it_and_keeps_what_it_wrote() {
    if !Command::new("unshare")
        .args(["-m", "true"])
        .status()
        .is_ok_and(|s| s.success())
    {
        println!("skipped: no mount namespace here (unshare -m needs root)");
        return;
    }
    let svc = Service::start(HWGW, "record-full", &[] as &[&str], &[]).unwrap();
    let mnt = svc.dir().join("small");
    std::fs::create_dir(&mnt).unwrap();
    let copy = svc.dir().join("kept.mcap");
    // The tmpfs lives as long as the namespace: the file is copied out before it ends.
    let script = r#"mount -t tmpfs -o size=512k hwgw-full "$1" || exit 99
"$2" record "$1/rec.mcap" --devices --port follow --port blink --socket "$3"
rc=$?
cp "$1/rec.mcap" "$4"
exit $rc"#;
    let out = Command::new("unshare")
        .args(["-m", "sh", "-c", script, "sh"])
        .arg(&mnt)
        .arg(HWGW)
        .arg(&svc.socket)
        .arg(&copy)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(99), "mount: {err}");
    assert!(!out.status.success(), "{err}");
    let path = format!("{}/rec.mcap", mnt.display());
    assert!(
        err.contains(&format!(
            "{path}: writing the recording failed: no space left on device (ENOSPC)"
        )),
        "{err}"
    );
    assert!(err.contains("is complete: "), "{err}");

    let mut d = testkit::mcapread::read(&copy).unwrap();
    // Completed where it was cut, without a summary (MCAP's is optional): no statistics
    // to count from.
    let kept: u64 = d.topics.values().map(|t| t.messages.len() as u64).sum();
    d.message_count = kept;
    check_shapes(&d);
    let meta = &d.metadata["hwgw.recording"];
    assert!(meta["error"].contains("ENOSPC"), "{meta:?}");
    assert!(meta["ended"].starts_with("error: "), "{meta:?}");
    assert!(kept > 1000, "{kept} messages kept");
    assert!(
        err.contains(&format!("{kept} messages")),
        "{err}: {kept} messages"
    );
    let unwritten: u64 = meta["unwritten"].parse().unwrap();
    assert!(unwritten > 0, "{meta:?}");
    // The chunks kept are the first ones: each port's samples run on without a gap from
    // the start (the demo's inputs every 20 ms).
    let ch0 = topic(&d, "/sim0/ai/ch0");
    assert!(
        ch0.times.windows(2).all(|w| w[1] - w[0] < 100 * MS),
        "a gap: the file lost a chunk in the middle"
    );

    // Cut short of its end: drawn, and said to be cut after so many messages.
    let bytes = std::fs::read(&copy).unwrap();
    let cut = svc.dir().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() - 10]).unwrap();
    let pic = svc.dir().join("cut.png");
    let said = svc
        .out(&["plot", cut.to_str().unwrap(), "-o", pic.to_str().unwrap()])
        .unwrap();
    assert!(
        said.contains(&format!("(cut after {kept} messages: ")),
        "{said}"
    );

    // A complete recording that holds no message: told apart from a cut one.
    let empty = svc.dir().join("empty.mcap");
    let said = svc
        .out(&[
            "record",
            empty.to_str().unwrap(),
            "--port",
            "sim0.ai.ch0",
            "--no-steps",
            "--trigger",
            "sim0.ai.ch0 > 1000",
            "--duration",
            "100ms",
        ])
        .unwrap();
    assert!(said.contains("0 messages"), "{said}");
    let o = svc.cli(&[
        "plot",
        empty.to_str().unwrap(),
        "-o",
        svc.dir().join("empty.png").to_str().unwrap(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && e.contains("nothing to plot: no messages: the recording is complete and empty"),
        "{e}"
    );
    // Cut within its first chunk (the schemas and channels): no message at all.
    std::fs::write(&cut, &bytes[..100]).unwrap();
    let o = svc.cli(&[
        "plot",
        cut.to_str().unwrap(),
        "-o",
        svc.dir().join("early.png").to_str().unwrap(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("nothing to plot: cut after 0 messages: "),
        "{e}"
    );
}
