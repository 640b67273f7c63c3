//! The reporter records chosen ports of other components to CSV.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;

fn deployment(file: &std::path::Path, extra: &str) -> String {
    format!(
        r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 2
[card.sim]
digital_inputs = 2
digital_outputs = 2
digital_loopback = true
[[card.sim.analog_in]]
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}
waveform = {{ kind = "ramp", from = -10.0, to = 10.0, period = 1.0 }}

[[component]]
name = "rec"
type = "reporter"
activity = {{ type = "periodic", period_ms = 10 }}
properties = {{ ports = ["sim0.ai.ch0", "sim0.di.bit1"], file = "{}"{extra} }}
"#,
        file.display()
    )
}

#[test]
fn records_ports_to_csv() {
    let dir = std::env::temp_dir().join(format!("hwgw-reporter-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("rec.csv");
    let text = deployment(&csv, "");
    let d = Deployment::parse(&text, "r.toml").unwrap();
    let gw = Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let rec = gw.runtime().component("rec").unwrap();
    testkit::wait_until("a dozen reporter steps", || rec.stats().steps >= 12);
    gw.shutdown();
    let content = std::fs::read_to_string(&csv).unwrap();
    let mut lines = content.lines();
    assert_eq!(lines.next(), Some("time_s,sim0.ai.ch0,sim0.di.bit1"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.len() >= 10, "{} rows after 12 steps", rows.len());
    let mut times = Vec::new();
    let mut ramp = Vec::new();
    // A port that has not delivered yet leaves its cell empty; after that, every row is full.
    let full: Vec<&Vec<&str>> = rows
        .iter()
        .filter(|r| r.iter().all(|c| !c.is_empty()))
        .collect();
    assert!(
        full.len() + 3 >= rows.len(),
        "only the first rows may have gaps: {rows:?}"
    );
    for r in full {
        assert_eq!(r.len(), 3, "{r:?}");
        times.push(r[0].parse::<f64>().unwrap());
        ramp.push(r[1].parse::<f64>().unwrap());
        assert_eq!(r[2], "false");
    }
    assert!(
        times.windows(2).all(|w| w[1] > w[0]),
        "time stamps increase"
    );
    assert!(ramp.iter().all(|v| (-10.0..=10.0).contains(v)));
    assert!(ramp.windows(2).any(|w| w[1] != w[0]), "the ramp moves");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_reporter_naming_a_missing_port_fails_to_configure() {
    let dir = std::env::temp_dir();
    let text = deployment(&dir.join("never.csv"), "").replace("sim0.di.bit1", "sim0.di.bit9");
    let d = Deployment::parse(&text, "r.toml").unwrap();
    let problems = Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin())
        .err()
        .unwrap();
    assert_eq!(problems.len(), 1);
    assert_eq!(
        problems[0].to_string(),
        "r.toml:14:1: component[0]: component \"rec\": configure_hook failed: \"sim0.di\" has no port \"bit9\"; it has: bit0, bit1"
    );
}

/// A report named by a link (to a root-only file, as an attacker would plant in /tmp), a
/// FIFO or another user's file is refused — by `check`/build when it is there already, and
/// at start when it was planted after — and what it named is left as it was.
#[test]
fn a_report_never_goes_through_a_link_nor_onto_a_file_not_its_own() {
    use std::os::unix::fs::PermissionsExt;
    let dir = testkit::TempDir::new("reporter-link");
    let secret = dir.path().join("secret");
    std::fs::write(&secret, "root only\n").unwrap();
    std::fs::set_permissions(&secret, std::fs::Permissions::from_mode(0o600)).unwrap();
    let build = |csv: &std::path::Path| {
        let text = deployment(csv, "");
        let d = Deployment::parse(&text, "r.toml").unwrap();
        Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin())
    };
    let refused = |csv: &std::path::Path, why: &str| {
        let problems = build(csv).err().expect("refused");
        let text = problems[0].to_string();
        assert!(
            text.contains(&csv.display().to_string()) && text.contains(why),
            "{text}"
        );
    };
    let link = dir.path().join("link.csv");
    std::os::unix::fs::symlink(&secret, &link).unwrap();
    refused(&link, "is a symbolic link: refused");
    let fifo = dir.path().join("fifo.csv");
    nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
    refused(&fifo, "is a FIFO, not a regular file");
    // Only root can give a file away; the other checks hold for every user.
    let root = nix::unistd::geteuid().is_root();
    let theirs = dir.path().join("theirs.csv");
    if root {
        std::fs::write(&theirs, "theirs\n").unwrap();
        std::os::unix::fs::chown(&theirs, Some(65534), None).unwrap();
        refused(&theirs, "belongs to uid 65534");
    }

    // Planted between the check and the start: the open itself refuses.
    let late = dir.path().join("late.csv");
    let gw = build(&late).unwrap();
    std::os::unix::fs::symlink(&secret, &late).unwrap();
    let e = gw.start().expect_err("a link planted after the check");
    assert!(e.to_string().contains("is a symbolic link"), "{e}");
    gw.shutdown();
    assert_eq!(std::fs::read_to_string(&secret).unwrap(), "root only\n");
    assert_eq!(
        std::fs::metadata(&secret).unwrap().permissions().mode() & 0o777,
        0o600
    );
    if root {
        let later = dir.path().join("later.csv");
        let gw = build(&later).unwrap();
        std::fs::write(&later, "theirs\n").unwrap();
        std::os::unix::fs::chown(&later, Some(65534), None).unwrap();
        let e = gw
            .start()
            .expect_err("another's file planted after the check");
        assert!(e.to_string().contains("belongs to uid 65534"), "{e}");
        gw.shutdown();
        assert_eq!(std::fs::read_to_string(&later).unwrap(), "theirs\n");
        assert_eq!(std::fs::read_to_string(&theirs).unwrap(), "theirs\n");
    }
}

/// A report of its own is rewritten at each start (a restarted service writes it anew).
#[test]
fn a_report_of_its_own_is_rewritten_at_start() {
    let dir = testkit::TempDir::new("reporter-again");
    let csv = dir.path().join("rec.csv");
    std::fs::write(
        &csv,
        "an old report that is longer than the new header\n".repeat(50),
    )
    .unwrap();
    let text = deployment(&csv, "");
    let d = Deployment::parse(&text, "r.toml").unwrap();
    let gw = Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let rec = gw.runtime().component("rec").unwrap();
    testkit::wait_until("two reporter steps", || rec.stats().steps >= 2);
    gw.shutdown();
    let content = std::fs::read_to_string(&csv).unwrap();
    assert!(
        content.starts_with("time_s,sim0.ai.ch0,sim0.di.bit1\n"),
        "{content}"
    );
    assert!(!content.contains("an old report"));
}
