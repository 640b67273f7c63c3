//! Peers the tests download or build, kept once per target directory: made into a
//! temporary path and renamed, so tests running at once each see a whole file.

use std::io;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Where downloaded and built peers are kept: `$CARGO_TARGET_DIR/peers`, or this
/// workspace's `target/peers`.
pub(crate) fn peer_dir() -> PathBuf {
    kernel_rig::rig_dir()
        .parent()
        .map_or_else(|| PathBuf::from("target/peers"), |t| t.join("peers"))
}

/// An error saying `what`.
pub(crate) fn fail(what: impl std::fmt::Display) -> io::Error {
    io::Error::other(what.to_string())
}

/// Makes `path` by `make` (into a temporary path beside it, then renamed: tests running
/// at once each get a whole file) unless it is there.
pub(crate) fn cached(
    path: &Path,
    make: impl FnOnce(&Path) -> io::Result<()>,
) -> io::Result<PathBuf> {
    if path.is_file() {
        return Ok(path.to_path_buf());
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    make(&tmp)?;
    std::fs::rename(&tmp, path)?;
    Ok(path.to_path_buf())
}

/// Runs `cmd`; its output in the error when it fails.
pub(crate) fn run(cmd: &mut Command) -> io::Result<()> {
    let out = cmd.output().map_err(|e| fail(format!("{cmd:?}: {e}")))?;
    if !out.status.success() {
        return Err(fail(format!(
            "{cmd:?}: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    Ok(())
}
