//! ThreadScope recorded by the real `hwgw` binary (`thread_scope_vcd`), read back by
//! sigrok-cli.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use testkit::{Service, TempDir, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// `thread_scope_vcd` on the demo: `check` creates no file; `run` records every thread's
/// pulses into `scope-1.vcd`, read back by sigrok-cli after SIGTERM (each signal ends low);
/// each restart records into the next number (a restart never finds its file taken), and
/// the last `thread_scope_vcd_keep` files are kept.
#[test]
fn thread_scope_records_a_vcd_that_sigrok_reads() {
    let dir = TempDir::new("scope-vcd-gw");
    let config = dir.path().join("demo.toml");
    let vcd = dir.path().join("scope-1.vcd");
    std::fs::write(
        &config,
        format!(
            "thread_scope_vcd = \"scope.vcd\"\nthread_scope_vcd_keep = 2\n{}",
            hwgw::DEMO
        ),
    )
    .unwrap();
    let check = || testkit::service::check(HWGW, &config);
    let out = check();
    assert!(out.status.success(), "{out:?}");
    let files = || {
        let mut v: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".vcd"))
            .collect();
        v.sort();
        v
    };
    assert!(files().is_empty(), "check created the recording");

    let svc = Service::start(HWGW, "scope-vcd", &[&config], &[]).unwrap();
    let blink_pulses = || {
        let text = std::fs::read_to_string(&vcd).unwrap_or_default();
        // A batch being written may end mid-line: not yet, then.
        testkit::vcd::read(&text).ok().and_then(|s| {
            s.values()
                .find(|s| s.name.ends_with("_blink"))
                .map(|s| s.rising)
        })
    };
    wait_until("three blink steps recorded", || {
        blink_pulses().is_some_and(|n| n >= 3)
    });
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(
        stopped.log.contains("ThreadScope recording ended"),
        "{}",
        stopped.log
    );

    let text = std::fs::read_to_string(&vcd).unwrap();
    assert!(
        text.contains("dropped (queue full) 0, unmapped (thread 64 or more) 0"),
        "{}",
        text.lines().rev().take(3).collect::<Vec<_>>().join("\n")
    );
    let signals = testkit::vcd::read(&text).unwrap();
    assert!(signals.values().all(|s| !s.high), "a bit left high");
    for s in signals.values().filter(|s| s.rising > 0) {
        assert_eq!(
            testkit::vcd::sigrok_rising_edges(&vcd, &s.name).unwrap(),
            s.rising,
            "{}",
            s.name
        );
    }
    // The card's bus side, blink and follow stepped, each on a thread named after it.
    for name in ["_sim0", "_blink", "_follow"] {
        assert!(
            signals
                .values()
                .any(|s| s.name.ends_with(name) && s.rising > 0),
            "{name}: {signals:?}"
        );
    }
    // Restarted (as systemd does): each run its own new file, the last two kept.
    assert!(check().status.success());
    for n in [2, 3] {
        let svc = Service::start(HWGW, "scope-vcd-again", &[&config], &[]).unwrap();
        let stopped = svc.terminate();
        assert!(stopped.status.success(), "{}", stopped.log);
        assert!(
            stopped.log.contains(&format!("scope-{n}.vcd")),
            "{}",
            stopped.log
        );
    }
    assert_eq!(files(), ["scope-2.vcd", "scope-3.vcd"]);
    for f in files() {
        let text = std::fs::read_to_string(dir.path().join(&f)).unwrap();
        assert!(
            text.contains("dropped (queue full) 0"),
            "{f} was not completed"
        );
    }
}
