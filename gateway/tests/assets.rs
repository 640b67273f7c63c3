//! `hwgw generate-assets DIR` (hidden; what the Debian package is built with): a manual
//! page for hwgw and each visible subcommand, and bash, zsh and fish completions, all from
//! the CLI's own definition; the hidden subcommand in none of them.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

#[test]
fn every_visible_subcommand_gets_a_page_and_the_hidden_one_none() {
    let dir = testkit::TempDir::new("assets");
    let out = std::process::Command::new(HWGW)
        .arg("generate-assets")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let names: Vec<String> = walk(dir.path())
        .iter()
        .filter_map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    for want in [
        "hwgw.1",
        "hwgw-status.1",
        "hwgw-run.1",
        "hwgw-reload.1",
        "hwgw.bash",
        "_hwgw",
        "hwgw.fish",
    ] {
        assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
    }
    assert!(!names.iter().any(|n| n.contains("generate")), "{names:?}");
    assert!(!names.iter().any(|n| n == "hwgw-help.1"), "{names:?}");
    let page = std::fs::read_to_string(dir.path().join("man/hwgw.1")).unwrap();
    assert!(
        page.contains("hwgw\\-status(1)") && page.contains(".SH FILES"),
        "{page}"
    );
    let bash = std::fs::read_to_string(dir.path().join("completions/hwgw.bash")).unwrap();
    assert!(bash.contains("status") && !bash.contains("generate-assets"));
}

/// Every file under `dir`.
fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut files = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            files.extend(walk(&p));
        } else {
            files.push(p);
        }
    }
    files
}
