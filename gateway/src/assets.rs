//! `hwgw generate-assets DIR` (hidden from `--help`): the manual pages and shell
//! completions of the Debian package, generated from the command line's own clap
//! definition when the package is built (`packaging/build-deb.sh`), so they cannot drift
//! from the binary they ship with.
//!
//! Writes `DIR/man/hwgw.1` and one page per visible subcommand (`hwgw-status.1`, …;
//! clap_mangen), and `DIR/completions/` for bash (`hwgw.bash`), zsh (`_hwgw`) and fish
//! (`hwgw.fish`; clap_complete). Hidden subcommands appear in neither.

use clap_complete::Shell;
use clap_mangen::Man;
use clap_mangen::roff::{Roff, bold, roman};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Why the assets could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{}: {source}", path.display())]
pub struct AssetsError {
    /// The file or directory.
    path: PathBuf,
    /// What went wrong.
    source: std::io::Error,
}

/// The files the package puts beside the binary, for the FILES section of `hwgw(1)`.
const FILES: [(&str, &str); 4] = [
    (
        "/etc/hwgw/hwgw.toml",
        "The deployment the hwgw service runs (a conffile; the package installs the demo on \
         simulated cards). Check a change with hwgw check, apply it with systemctl reload hwgw.",
    ),
    (
        "/run/hwgw/hwgw.sock",
        "The service's control socket, open to the members of group hwgw.",
    ),
    (
        "/usr/lib/systemd/system/hwgw.service",
        "The unit: systemctl status hwgw; the log: journalctl -u hwgw.",
    ),
    (
        "/usr/share/doc/hwgw/examples/",
        "Commented example deployments, one per bus.",
    ),
];

/// The `hwgw(1)` page with a FILES section after what clap_mangen renders.
fn main_page(man: &Man) -> Vec<u8> {
    let mut page = Vec::new();
    // Rendering into memory cannot fail.
    let _ = man.render(&mut page);
    let mut files = Roff::new();
    files.control("SH", ["FILES"]);
    for (path, what) in FILES {
        files
            .control("TP", [])
            .text([bold(path)])
            .text([roman(what)]);
    }
    page.extend_from_slice(files.to_roff().as_bytes());
    page
}

fn write(path: PathBuf, bytes: &[u8]) -> Result<PathBuf, AssetsError> {
    match std::fs::write(&path, bytes) {
        Ok(()) => Ok(path),
        Err(source) => Err(AssetsError { path, source }),
    }
}

fn create_dir(path: PathBuf) -> Result<PathBuf, AssetsError> {
    match std::fs::create_dir_all(&path) {
        Ok(()) => Ok(path),
        Err(source) => Err(AssetsError { path, source }),
    }
}

/// `cmd` (not yet built) without its hidden subcommands, which clap_complete would offer.
fn without_hidden(cmd: &clap::Command) -> clap::Command {
    let mut out = clap::Command::new("hwgw").version(env!("CARGO_PKG_VERSION"));
    if let Some(about) = cmd.get_about() {
        out = out.about(about.clone());
    }
    for a in cmd.get_arguments() {
        out = out.arg(a.clone());
    }
    for g in cmd.get_groups() {
        out = out.group(g.clone());
    }
    for s in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        out = out.subcommand(s.clone());
    }
    out
}

/// Writes the manual pages and completions of `cmd` (the `hwgw` command line) under
/// `dir`; returns the files written.
pub(crate) fn generate(cmd: clap::Command, dir: &Path) -> Result<Vec<PathBuf>, AssetsError> {
    let mut completed = without_hidden(&cmd);
    let mut cmd = cmd.disable_help_subcommand(true);
    cmd.build();
    let source = format!("hwgw {}", env!("CARGO_PKG_VERSION"));
    let man = |c: clap::Command| Man::new(c).source(source.clone()).manual("hwgw manual");
    let man_dir = create_dir(dir.join("man"))?;
    let mut written = Vec::new();
    let main = man(cmd.clone());
    written.push(write(man_dir.join(main.get_filename()), &main_page(&main))?);
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        let page = man(sub.clone());
        let mut text = Vec::new();
        // Into memory: cannot fail.
        let _ = page.render(&mut text);
        written.push(write(man_dir.join(page.get_filename()), &text)?);
    }
    let completions = create_dir(dir.join("completions"))?;
    for shell in [Shell::Bash, Shell::Zsh, Shell::Fish] {
        let mut script = Vec::new();
        clap_complete::generate(shell, &mut completed, "hwgw", &mut script);
        let name = clap_complete::Generator::file_name(&shell, "hwgw");
        written.push(write(completions.join(name), &script)?);
    }
    Ok(written)
}

/// `hwgw generate-assets DIR`: prints each file written, or the error and exit code 1.
pub(crate) fn run(cmd: clap::Command, dir: &Path) -> ExitCode {
    match generate(cmd, dir) {
        Ok(files) => {
            for f in files {
                println!("{}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("hwgw: generate-assets: {e}");
            ExitCode::FAILURE
        }
    }
}
