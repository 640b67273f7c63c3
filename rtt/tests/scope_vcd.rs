//! ThreadScope recorded into a VCD file: each thread's pulses in the file equal the steps
//! the runtime counted — read by testkit's own reading of the file and by sigrok-cli's
//! edge counter (an independent VCD reader, installed when missing) — an existing file is
//! never overwritten, and a second recording is refused.

use device_interface::Registry;
use rtt::activity::ActivitySpec;
use rtt::{Component, Runtime, RuntimeOptions};
use std::sync::Arc;
use std::time::Duration;
use testkit::wait_until;

struct Idle;
impl Component for Idle {}

#[test]
fn each_threads_pulses_in_the_vcd_are_its_steps() {
    let dir = testkit::TempDir::new("scope-vcd");
    let file = dir.path().join("scope.vcd");
    let rt = Runtime::new(
        Arc::new(Registry::new()),
        RuntimeOptions {
            thread_scope_vcd: Some(file.clone()),
            ..RuntimeOptions::default()
        },
    )
    .unwrap();
    let add = |name: &str, ms: u64| {
        rt.add(
            name,
            ActivitySpec::periodic(Duration::from_millis(ms)),
            rtt::InitialState::Stopped,
            |_| Ok(Idle),
        )
        .unwrap()
    };
    let (fast, slow) = (add("fast", 1), add("slow", 3));
    fast.start().unwrap();
    slow.start().unwrap();
    wait_until("60 fast and 20 slow steps", || {
        fast.stats().steps >= 60 && slow.stats().steps >= 20
    });
    fast.stop().unwrap();
    slow.stop().unwrap();
    let steps = |t: &rtt::TaskContext| t.stats().steps;
    let (fast_steps, slow_steps) = (steps(&fast), steps(&slow));
    let counts = rt.thread_scope().vcd().unwrap().finish().unwrap();
    assert_eq!(counts.dropped, 0, "{counts:?}");
    assert_eq!(counts.unmapped, 0, "{counts:?}");

    let text = std::fs::read_to_string(&file).unwrap();
    let signals = testkit::vcd::read(&text).unwrap();
    assert_eq!(signals.len(), 64, "a signal per possible thread");
    let by_name = |name: &str| {
        let s = signals
            .values()
            .find(|s| s.name == name)
            .unwrap_or_else(|| panic!("no signal {name}: {signals:?}"));
        (s.rising, s.high)
    };
    let thread = |t: &rtt::TaskContext| t.activity().thread_number().unwrap();
    let (fast_name, slow_name) = (
        format!("t{}_fast", thread(&fast)),
        format!("t{}_slow", thread(&slow)),
    );
    assert_eq!(by_name(&fast_name), (fast_steps, false));
    assert_eq!(by_name(&slow_name), (slow_steps, false));
    let pulses: u64 = signals.values().map(|s| s.rising).sum();
    assert_eq!(counts.written, 2 * pulses, "{counts:?}");

    // An independent reader sees the same pulses.
    let sigrok = |name: &str| testkit::vcd::sigrok_rising_edges(&file, name).unwrap();
    assert_eq!(sigrok(&fast_name), fast_steps);
    assert_eq!(sigrok(&slow_name), slow_steps);
    println!(
        "ThreadScope VCD: {fast_name} {fast_steps} pulses, {slow_name} {slow_steps} pulses, \
         {} edges written ({} late), sigrok-cli counts the same",
        counts.written, counts.late
    );
}

#[test]
fn an_existing_file_is_never_overwritten() {
    let dir = testkit::TempDir::new("scope-vcd-exists");
    let file = dir.path().join("keep.vcd");
    std::fs::write(&file, "precious").unwrap();
    let err = Runtime::new(
        Arc::new(Registry::new()),
        RuntimeOptions {
            thread_scope_vcd: Some(file.clone()),
            ..RuntimeOptions::default()
        },
    )
    .err()
    .expect("refused");
    let text = err.to_string();
    assert!(
        text.contains("keep.vcd") && text.contains("exists"),
        "{text}"
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "precious");
    let missing = dir.path().join("no/such/folder/x.vcd");
    let err = Runtime::new(
        Arc::new(Registry::new()),
        RuntimeOptions {
            thread_scope_vcd: Some(missing),
            ..RuntimeOptions::default()
        },
    )
    .err()
    .expect("refused");
    assert!(err.to_string().contains("no/such/folder/x.vcd"), "{err}");
}

#[test]
fn one_recording_per_thread_scope() {
    let dir = testkit::TempDir::new("scope-vcd-twice");
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    assert!(!rt.thread_scope().is_on());
    rt.thread_scope()
        .record_vcd(&dir.path().join("a.vcd"))
        .unwrap();
    assert!(rt.thread_scope().is_on());
    let err = rt
        .thread_scope()
        .record_vcd(&dir.path().join("b.vcd"))
        .err()
        .expect("refused");
    assert!(
        err.to_string().contains("records into a file already"),
        "{err}"
    );
    assert!(!dir.path().join("b.vcd").exists());
    // No step, no edge: the file is still a valid VCD with every signal low.
    let counts = rt.thread_scope().vcd().unwrap().finish().unwrap();
    assert_eq!(counts.written, 0);
    let text = std::fs::read_to_string(dir.path().join("a.vcd")).unwrap();
    let signals = testkit::vcd::read(&text).unwrap();
    assert_eq!(signals.len(), 64);
    assert!(signals.values().all(|s| s.rising == 0 && !s.high));
}

/// Each run writes a new numbered file beside the name given, the highest number the
/// newest; the last `keep` are kept. What is not a file of this process's own under such a
/// name — a link planted there — is neither counted, nor removed, nor followed.
#[test]
fn numbered_recordings_rotate_keeping_the_last_ones() {
    let dir = testkit::TempDir::new("scope-vcd-rotate");
    let base = dir.path().join("threads.vcd");
    let precious = dir.path().join("precious");
    std::fs::write(&precious, "keep me").unwrap();
    let run = |expect: u64| {
        let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
        let trace = rt.thread_scope().record_vcd_numbered(&base, 3).unwrap();
        assert_eq!(
            trace.path(),
            rtt::scope::vcd::files::numbered(&base, expect)
        );
        trace.finish().unwrap();
    };
    let numbered = || {
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("threads"))
            .collect();
        names.sort();
        names
    };
    for n in 1..=5 {
        run(n);
    }
    assert_eq!(
        numbered(),
        ["threads-3.vcd", "threads-4.vcd", "threads-5.vcd"]
    );
    // Every one kept is a whole recording.
    for name in numbered() {
        let text = std::fs::read_to_string(dir.path().join(&name)).unwrap();
        assert_eq!(testkit::vcd::read(&text).unwrap().len(), 64, "{name}");
    }
    let link = dir.path().join("threads-6.vcd");
    std::os::unix::fs::symlink(&precious, &link).unwrap();
    run(7);
    assert_eq!(
        numbered(),
        [
            "threads-4.vcd",
            "threads-5.vcd",
            "threads-6.vcd",
            "threads-7.vcd"
        ]
    );
    assert!(std::fs::symlink_metadata(&link).unwrap().is_symlink());
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "keep me");
}

/// A link at the name — to a file or dangling — is refused, never followed: what it
/// points to is left as it was, or not made.
#[test]
fn a_recording_never_goes_through_a_link() {
    let dir = testkit::TempDir::new("scope-vcd-link");
    let precious = dir.path().join("precious");
    std::fs::write(&precious, "keep me").unwrap();
    let link = dir.path().join("scope.vcd");
    std::os::unix::fs::symlink(&precious, &link).unwrap();
    let dangling = dir.path().join("dangling.vcd");
    std::os::unix::fs::symlink(dir.path().join("made"), &dangling).unwrap();
    for path in [&link, &dangling] {
        let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
        let e = rt.thread_scope().record_vcd(path).err().expect("refused");
        assert!(e.to_string().contains("is a symbolic link: refused"), "{e}");
    }
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "keep me");
    assert!(!dir.path().join("made").exists());
}
