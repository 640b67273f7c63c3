//! The workspace keeps its shape: no two modules of a crate import each other, and no
//! function in the gateway is longer than ~120 lines.

use std::path::{Path, PathBuf};
use testkit::layout::{ModuleGraph, long_functions};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Every crate's `src` folder in the workspace.
fn crate_sources() -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![workspace()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            let name = e.file_name().to_string_lossy().into_owned();
            if !p.is_dir() || name.starts_with('.') || name == "target" {
                continue;
            }
            if p.join("Cargo.toml").is_file() && p.join("src").is_dir() {
                out.push(p.join("src"));
            }
            stack.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn no_two_modules_of_a_crate_import_each_other() {
    let sources = crate_sources();
    assert!(sources.len() >= 8, "found only {sources:?}");
    let mut problems = Vec::new();
    for src in &sources {
        let graph = ModuleGraph::read(src).unwrap();
        for cycle in graph.cycles() {
            problems.push(format!("{}: {}", src.display(), cycle.join(" -> ")));
        }
    }
    assert!(
        problems.is_empty(),
        "import cycles:\n{}",
        problems.join("\n")
    );
}

#[test]
fn no_function_in_the_gateway_is_over_120_lines() {
    let long = long_functions(&workspace().join("gateway/src"), 120).unwrap();
    assert!(long.is_empty(), "{long:#?}");
}
