//! The user's guide cannot drift from the code: every fenced `toml` block of `README.md`
//! and `docs/*.md` goes through the real `hwgw check`, as its marker says, and none is
//! skipped; the guide's links lead somewhere; its protocol table is the protocol's.
//!
//! A `toml` block is classified by the HTML comment on the line before it (see
//! `docs/README.md`, "How the examples are checked"):
//!
//! - `<!-- check: whole -->`: a whole deployment, which `hwgw check` passes;
//! - `<!-- check: after config/demo.toml -->`: a fragment, appended to that file;
//! - either followed by `; fails `TEXT`` (once or more) and a reason: `hwgw check` refuses
//!   it, every error line it prints holds one of the TEXTs and each TEXT is in one;
//! - `<!-- check: cargo manifest -->`: part of a `Cargo.toml`, which must parse.
//!
//! `hwgw check` runs in a temporary directory holding copies of `config/can.dbc`,
//! `gateway/tests/data/*` and the CANopen tests' EDS files, so a block names those files as
//! a deployment in `config/` does.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use std::path::{Path, PathBuf};
use std::process::Command;
use testkit::TempDir;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// The repository's root.
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The guide's pages: the front page and every page under `docs/`, relative to the root.
fn pages() -> Vec<PathBuf> {
    let mut pages = vec![PathBuf::from("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(repo().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .map(|p| p.strip_prefix(repo()).unwrap().to_path_buf())
        .collect();
    docs.sort();
    pages.extend(docs);
    pages
}

/// A fenced block of a page.
struct Block {
    /// The page, relative to the root.
    page: PathBuf,
    /// The line of its opening fence (1-based).
    line: usize,
    /// The fence's info string (`toml`, `sh`, …).
    info: String,
    /// The last non-blank line before the fence.
    before: String,
    /// Its text.
    text: String,
}

impl Block {
    fn at(&self) -> String {
        format!("{}:{}", self.page.display(), self.line)
    }
}

/// The fenced blocks of `page`.
fn blocks(page: &Path) -> Vec<Block> {
    let text = std::fs::read_to_string(repo().join(page)).unwrap();
    let mut out = Vec::new();
    let mut open: Option<Block> = None;
    let mut before = String::new();
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(info)) => {
                open = Some(Block {
                    page: page.to_path_buf(),
                    line: i + 1,
                    info: info.trim().to_string(),
                    before: before.clone(),
                    text: String::new(),
                });
            }
            (Some(_), Some(rest)) if rest.trim().is_empty() => {
                out.extend(open.take());
                // A block right after another is not marked by what preceded that one.
                before = line.trim().to_string();
            }
            (Some(b), _) => {
                b.text.push_str(line);
                b.text.push('\n');
            }
            (None, None) => {
                if !line.trim().is_empty() {
                    before = line.trim().to_string();
                }
            }
        }
    }
    assert!(open.is_none(), "{}: a fence never closed", page.display());
    out
}

/// What a block's marker asks.
#[derive(Debug)]
enum Base {
    /// A whole deployment.
    Whole,
    /// A fragment appended to this file (relative to the root).
    After(PathBuf),
    /// Part of a Cargo manifest.
    Cargo,
}

#[derive(Debug)]
struct Marker {
    base: Base,
    /// Texts the errors must hold; empty: `hwgw check` passes.
    fails: Vec<String>,
}

/// The marker in `comment` (`<!-- check: … -->`), or why it is none.
fn marker(comment: &str) -> Result<Marker, String> {
    let body = comment
        .strip_prefix("<!--")
        .and_then(|c| c.strip_suffix("-->"))
        .and_then(|c| c.trim().strip_prefix("check:"))
        .ok_or("no `<!-- check: … -->` comment on the line before it")?
        .trim();
    let (base, rest) = body.split_once(';').unwrap_or((body, ""));
    let base = match base.trim() {
        "whole" => Base::Whole,
        "cargo manifest" => Base::Cargo,
        b => match b.strip_prefix("after ") {
            Some(file) if repo().join(file.trim()).is_file() => {
                Base::After(PathBuf::from(file.trim()))
            }
            Some(file) => return Err(format!("`after {file}`: no such file")),
            None => {
                return Err(format!(
                    "{b:?}: expected whole, after FILE or cargo manifest"
                ));
            }
        },
    };
    let mut fails = Vec::new();
    let mut rest = rest;
    while let Some(at) = rest.find("fails `") {
        let tail = &rest[at + "fails `".len()..];
        let end = tail
            .find('`')
            .ok_or("a `fails` text without its closing backtick")?;
        fails.push(tail[..end].to_string());
        rest = &tail[end + 1..];
    }
    if matches!(base, Base::Cargo) && !fails.is_empty() {
        return Err("a Cargo manifest is parsed, not checked: it cannot fail".into());
    }
    Ok(Marker { base, fails })
}

/// A scratch directory (named after `tag`: each test its own) with the files the guide's
/// deployments name.
fn scratch(tag: &str) -> TempDir {
    let dir = TempDir::new(tag);
    let mut files = vec![
        repo().join("config/can.dbc"),
        repo().join("config/interlock.lua"),
    ];
    for dir in ["gateway/tests/data", "drivers/canopen/tests/eds"] {
        for e in std::fs::read_dir(repo().join(dir)).unwrap() {
            files.push(e.unwrap().path());
        }
    }
    for f in files.iter().filter(|f| f.is_file()) {
        std::fs::copy(f, dir.path().join(f.file_name().unwrap())).unwrap();
    }
    dir
}

/// Checks one `toml` block as its marker says; the reason it does not hold, if it does not.
fn check(block: &Block, dir: &Path) -> Result<(), String> {
    let m = marker(&block.before)?;
    let text = match &m.base {
        Base::Cargo => {
            let table: toml::Table = toml::from_str(&block.text).map_err(|e| e.to_string())?;
            const SECTIONS: [&str; 13] = [
                "package",
                "dependencies",
                "dev-dependencies",
                "build-dependencies",
                "features",
                "lib",
                "bin",
                "test",
                "bench",
                "workspace",
                "lints",
                "target",
                "profile",
            ];
            return match table.keys().find(|k| !SECTIONS.contains(&k.as_str())) {
                Some(k) => Err(format!("[{k}] is no section of a Cargo manifest")),
                None => Ok(()),
            };
        }
        Base::Whole => block.text.clone(),
        Base::After(file) => {
            let base = std::fs::read_to_string(repo().join(file)).unwrap();
            format!("{base}\n{}", block.text)
        }
    };
    let stem = block.page.file_stem().unwrap().to_string_lossy();
    let name = format!("{stem}-{}.toml", block.line);
    std::fs::write(dir.join(&name), text).unwrap();
    let out = Command::new(HWGW)
        .args(["check", &name])
        .current_dir(dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let said = || format!("hwgw check {name}:\n{stdout}{stderr}");
    if m.fails.is_empty() {
        return if out.status.success() {
            Ok(())
        } else {
            Err(format!("refused; {}", said()))
        };
    }
    if out.status.success() {
        return Err(format!("passed, but the marker expects errors; {}", said()));
    }
    // Errors are `FILE:LINE:COLUMN: key: message` lines (the log has lines of its own).
    let errors: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with(&format!("{name}:")))
        .collect();
    if errors.is_empty() {
        return Err(format!("no located error; {}", said()));
    }
    if let Some(e) = errors
        .iter()
        .find(|e| !m.fails.iter().any(|f| e.contains(f.as_str())))
    {
        return Err(format!(
            "an error the marker does not name: {e}; {}",
            said()
        ));
    }
    if let Some(f) = m
        .fails
        .iter()
        .find(|f| !errors.iter().any(|e| e.contains(f.as_str())))
    {
        return Err(format!("no error holds {f:?}; {}", said()));
    }
    Ok(())
}

#[test]
fn every_toml_block_of_the_guide_is_what_hwgw_check_says() {
    let dir = scratch("docs");
    let mut checked = 0;
    let mut wrong = Vec::new();
    for page in pages() {
        for b in blocks(&page) {
            if !b.info.to_ascii_lowercase().starts_with("toml") {
                continue;
            }
            checked += 1;
            if let Err(e) = check(&b, dir.path()) {
                wrong.push(format!("{}: {e}", b.at()));
            }
        }
    }
    assert!(wrong.is_empty(), "\n{}", wrong.join("\n\n"));
    // The guide has examples on every topic; none may quietly vanish from this count.
    assert!(checked >= 20, "only {checked} toml blocks found");
}

/// Every `lua` block of the guide is a whole script that loads: `hwgw check` of the demo
/// with a script component running it (its syntax, its top level, its ports declared,
/// the names it calls there). A block may use the demo's card `sim0` by name.
#[test]
fn every_lua_block_of_the_guide_loads_as_a_script() {
    let dir = scratch("docs-lua");
    let demo = std::fs::read_to_string(repo().join("config/demo.toml")).unwrap();
    let mut checked = 0;
    let mut wrong = Vec::new();
    for page in pages() {
        for b in blocks(&page) {
            if b.info != "lua" {
                continue;
            }
            checked += 1;
            let stem = b.page.file_stem().unwrap().to_string_lossy().into_owned();
            let lua = format!("{stem}-{}.lua", b.line);
            std::fs::write(dir.path().join(&lua), &b.text).unwrap();
            let toml = format!("{stem}-{}-lua.toml", b.line);
            let component = format!(
                "{demo}\n[[component]]\nname = \"doc_script\"\ntype = \"script\"\n\
                 activity = {{ type = \"periodic\", period_ms = 100 }}\n\
                 properties = {{ file = \"{lua}\" }}\n"
            );
            std::fs::write(dir.path().join(&toml), component).unwrap();
            let out = Command::new(HWGW)
                .args(["check", &toml])
                .current_dir(dir.path())
                .output()
                .unwrap();
            if !out.status.success() {
                wrong.push(format!(
                    "{}: {}",
                    b.at(),
                    String::from_utf8_lossy(&out.stderr)
                ));
            }
        }
    }
    assert!(wrong.is_empty(), "\n{}", wrong.join("\n\n"));
    assert!(checked >= 3, "only {checked} lua blocks found");
}

#[test]
fn a_block_without_a_marker_is_refused_not_skipped() {
    for comment in [
        "",
        "Some text.",
        "<!-- a note -->",
        "<!-- check: partly -->",
        "<!-- check: after config/nowhere.toml -->",
        "<!-- check: cargo manifest; fails `x` -->",
        "<!-- check: whole; fails `open -->",
    ] {
        assert!(marker(comment).is_err(), "{comment:?} was taken");
    }
    let m =
        marker("<!-- check: after config/demo.toml; fails `a \"b\"`; fails `c` — why -->").unwrap();
    assert!(matches!(m.base, Base::After(_)));
    assert_eq!(m.fails, ["a \"b\"", "c"]);
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, ' ' | '-' | '_'))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a page's headings (outside code blocks).
fn anchors(page: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(page).unwrap();
    let mut code = false;
    let mut out = Vec::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            code = !code;
        } else if !code && line.starts_with('#') {
            out.push(anchor(line.trim_start_matches('#')));
        }
    }
    out
}

#[test]
fn every_link_of_the_guide_leads_somewhere() {
    let mut broken = Vec::new();
    for page in pages() {
        let text = std::fs::read_to_string(repo().join(&page)).unwrap();
        let folder = repo().join(&page).parent().unwrap().to_path_buf();
        let mut rest = text.as_str();
        while let Some(at) = rest.find("](") {
            let tail = &rest[at + 2..];
            let Some(end) = tail.find(')') else { break };
            let link = &tail[..end];
            rest = &tail[end..];
            if link.contains("://") || link.starts_with("mailto:") {
                continue;
            }
            let (file, frag) = link.split_once('#').unwrap_or((link, ""));
            let target = if file.is_empty() {
                repo().join(&page)
            } else {
                folder.join(file)
            };
            if !target.exists() {
                broken.push(format!("{}: {link}: no such file", page.display()));
            } else if !frag.is_empty()
                && target.extension().is_some_and(|x| x == "md")
                && !anchors(&target).contains(&frag.to_string())
            {
                broken.push(format!("{}: {link}: no such heading", page.display()));
            }
        }
    }
    assert!(broken.is_empty(), "\n{}", broken.join("\n"));
}

#[test]
fn the_guide_shows_the_protocols_own_command_table() {
    let page = std::fs::read_to_string(repo().join("docs/control.md")).unwrap();
    for line in hwgw::protocol::Request::table().lines() {
        assert!(
            page.lines().any(|l| l == line),
            "docs/control.md lacks the line (it must show Request::table()):\n{line}"
        );
    }
}

#[test]
fn the_front_page_is_a_front_page() {
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(
        lines <= 150,
        "README.md has {lines} lines: the rest belongs in docs/"
    );
    // The two commands, exactly as .ci/run and a new user run them.
    for command in ["cargo run -p hwgw -- run", "cargo test --workspace"] {
        assert!(
            readme.lines().any(|l| l == command),
            "README.md lacks the line {command:?}"
        );
    }
}
