//! Properties from files and back, attributes and constants, through the command line:
//! `properties_file` applied in order before the inline `properties`, an error located in
//! the property file that has it; `save-properties` writes a new file (or replaces one
//! when asked), `load-properties` sets them all or none; an attribute is read and set by
//! name, a constant only read.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use testkit::{Service, TempDir};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw-example-custom");

fn deployment(files: &str) -> String {
    format!(
        r#"
[[card]]
name = "sim0"
driver = "sim"
[card.sim]
digital_outputs = 1

[[component]]
name = "threshold"
type = "threshold"
activity = {{ type = "non_periodic" }}
properties_file = [{files}]
properties = {{ hysteresis = 0.25 }}
"#
    )
}

#[test]
fn property_files_apply_in_order_and_errors_are_located_in_them() {
    let dir = TempDir::new("propfiles");
    std::fs::write(
        dir.path().join("base.toml"),
        "above = 1.0\nhysteresis = 0.5\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("site.toml"), "above = 3.5\n").unwrap();
    std::fs::write(dir.path().join("bad.toml"), "above = 1.0\n\nabove_x = 2\n").unwrap();
    let cfg = dir.path().join("d.toml");
    std::fs::write(&cfg, deployment("\"base.toml\", \"site.toml\"")).unwrap();
    let svc = Service::start(BIN, "propfiles-run", &[&cfg], &[]).unwrap();
    // site.toml over base.toml, the inline value over both.
    assert_eq!(
        svc.out(&["get", "threshold", "property:above"]).unwrap(),
        "3.5"
    );
    assert_eq!(
        svc.out(&["get", "threshold", "property:hysteresis"])
            .unwrap(),
        "0.25"
    );

    // Attributes by name; a constant is read, never written.
    assert_eq!(
        svc.out(&["get", "threshold", "attribute:switches"])
            .unwrap(),
        "0"
    );
    svc.out(&["set", "threshold", "attribute:switches", "7"])
        .unwrap();
    assert_eq!(
        svc.out(&["get", "threshold", "attribute:switches"])
            .unwrap(),
        "7"
    );
    assert_eq!(
        svc.out(&["get", "threshold", "attribute:kind"]).unwrap(),
        "\"comparator with hysteresis\""
    );
    let e = svc
        .out(&["set", "threshold", "attribute:kind", "x"])
        .unwrap_err();
    assert!(e.contains("a constant"), "{e}");

    // Saved whole into a new file; never over one unless asked.
    let saved = dir.path().join("saved.toml");
    svc.out(&["save-properties", "threshold", saved.to_str().unwrap()])
        .unwrap();
    let text = std::fs::read_to_string(&saved).unwrap();
    assert!(
        text.contains("above = 3.5") && text.contains("hysteresis = 0.25"),
        "{text}"
    );
    let e = svc
        .out(&["save-properties", "threshold", saved.to_str().unwrap()])
        .unwrap_err();
    assert!(e.contains("exists"), "{e}");
    // Loaded back after a change: all of them.
    svc.out(&["set", "threshold", "property:above", "9"])
        .unwrap();
    svc.out(&["load-properties", "threshold", saved.to_str().unwrap()])
        .unwrap();
    assert_eq!(
        svc.out(&["get", "threshold", "property:above"]).unwrap(),
        "3.5"
    );
    // A file with one bad name sets none.
    svc.out(&["set", "threshold", "property:above", "9"])
        .unwrap();
    let bad = dir.path().join("bad.toml");
    let e = svc
        .out(&["load-properties", "threshold", bad.to_str().unwrap()])
        .unwrap_err();
    assert!(e.contains("above_x"), "{e}");
    assert_eq!(
        svc.out(&["get", "threshold", "property:above"]).unwrap(),
        "9.0"
    );
    svc.out(&[
        "save-properties",
        "threshold",
        saved.to_str().unwrap(),
        "--replace",
    ])
    .unwrap();
    assert!(
        std::fs::read_to_string(&saved)
            .unwrap()
            .contains("above = 9.0")
    );
    assert!(svc.terminate().status.success());

    // A wrong name in a property file: located in that file, at its key.
    std::fs::write(&cfg, deployment("\"base.toml\", \"bad.toml\"")).unwrap();
    let out = testkit::service::check(BIN, &cfg);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    let bad = dir.path().join("bad.toml");
    assert!(
        err.contains(&format!(
            "{}:3:1: above_x: no property \"above_x\"",
            bad.display()
        )),
        "{err}"
    );
    // A file that is not there: at the deployment's key.
    std::fs::write(&cfg, deployment("\"gone.toml\"")).unwrap();
    let out = testkit::service::check(BIN, &cfg);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("component[0].properties_file[0]") && err.contains("gone.toml"),
        "{err}"
    );
}
