//! hwgw's Debian packages built for a test from the binary cargo built for it, the way
//! an operator's are built: `packaging/build-deb.sh --binary …` (which installs cargo-deb
//! at its pinned version when missing), once as version `…-1` and once more as `…-2` (an
//! upgrade), and lintian's verdict on the first.
//!
//! Built on the host before the kernel rig boots (the guest sees the host's files, so a
//! trial there installs them with apt): [`build`] on the host, [`first`], [`upgrade`] and
//! [`lintian_report`] in the guest. The packages use the system's gzip at its lightest
//! (`--compress-type gz --fast --compress-system`): the test binary is a debug build, 100
//! MB even stripped, which the emulated guest unpacks in 6 s from gzip where xz took 18.

use crate::peers::{LINTIAN, require};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Why the packages could not be built.
#[derive(Debug, thiserror::Error)]
pub enum DebError {
    /// A file or directory could not be made or read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// A command failed.
    #[error("{command}: {problem}")]
    Command {
        /// The command.
        command: String,
        /// What it said.
        problem: String,
    },
    /// A peer the packages need is missing (lintian).
    #[error(transparent)]
    Peer(#[from] crate::peers::PeerError),
    /// A directory that should hold one package holds none or several.
    #[error("{dir}: expected one .deb, found {found:?}")]
    NotOne {
        /// The directory.
        dir: PathBuf,
        /// The packages in it.
        found: Vec<PathBuf>,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DebError + '_ {
    move |source| DebError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Where the packages are: under the rig's directory, which the guest sees too.
pub fn dir() -> PathBuf {
    kernel_rig::rig_dir().join("hwgw-deb")
}

/// The first package (`…-1`).
pub fn first() -> Result<PathBuf, DebError> {
    only_deb(&dir().join("1"))
}

/// The same binary rebuilt as a higher version (`--deb-revision 2`).
pub fn upgrade() -> Result<PathBuf, DebError> {
    only_deb(&dir().join("2"))
}

/// What lintian said of the first package.
pub fn lintian_report() -> Result<String, DebError> {
    let path = dir().join("lintian.txt");
    std::fs::read_to_string(&path).map_err(io(&path))
}

fn only_deb(dir: &Path) -> Result<PathBuf, DebError> {
    let found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "deb"))
        .collect();
    match found.as_slice() {
        [one] => Ok(one.clone()),
        _ => Err(DebError::NotOne {
            dir: dir.to_path_buf(),
            found,
        }),
    }
}

fn run(cmd: &mut Command) -> Result<String, DebError> {
    let command = format!("{cmd:?}");
    let out = cmd.output().map_err(|e| DebError::Command {
        command: command.clone(),
        problem: e.to_string(),
    })?;
    if !out.status.success() {
        return Err(DebError::Command {
            command,
            problem: format!(
                "{}: {}{}",
                out.status,
                String::from_utf8_lossy(&out.stdout).trim(),
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The packages being built or used: held until dropped, so that a second test process
/// waits instead of rebuilding them under a guest that installs them.
#[derive(Debug)]
pub struct Built {
    _lock: std::fs::File,
}

/// Builds both packages from `binary` with the checkout's `packaging/build-deb.sh` (in
/// `repo`), and runs lintian on the first (installing lintian when missing). On the host.
pub fn build(repo: &Path, binary: &Path) -> Result<Built, DebError> {
    let dir = dir();
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let lock_path = dir.with_extension("lock");
    let lock = std::fs::File::create(&lock_path).map_err(io(&lock_path))?;
    lock.lock().map_err(io(&lock_path))?;
    let script = repo.join("packaging/build-deb.sh");
    for (sub, revision) in [("1", "1"), ("2", "2")] {
        let out = dir.join(sub);
        let _ = std::fs::remove_dir_all(&out);
        std::fs::create_dir_all(&out).map_err(io(&out))?;
        eprintln!("kernel_systemd: building the hwgw package, revision {revision}");
        run(Command::new(&script)
            .arg("--binary")
            .arg(binary)
            .arg("--output")
            .arg(&out)
            .args([
                "--deb-revision",
                revision,
                "--fast",
                "--compress-type",
                "gz",
            ])
            // The system's gzip: cargo-deb's own took over two minutes for it.
            .arg("--compress-system"))?;
        only_deb(&out)?;
    }
    require(&LINTIAN)?;
    // lintian exits non-zero on errors: its report is the verdict, read by the test.
    let deb = first()?;
    let out = Command::new("lintian")
        .args(["--tag-display-limit", "0"])
        .arg(&deb)
        .output()
        .map_err(|e| DebError::Command {
            command: "lintian".into(),
            problem: e.to_string(),
        })?;
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let path = dir.join("lintian.txt");
    std::fs::write(&path, report).map_err(io(&path))?;
    Ok(Built { _lock: lock })
}
