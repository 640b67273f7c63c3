//! The files of a ThreadScope recording, opened so that a path cannot be turned against
//! the process: created new (`O_CREAT | O_EXCL`: never an existing name, never another's
//! file), never through a symbolic link (`O_NOFOLLOW`), and checked to be a regular file
//! on the descriptor just opened (`fstat`).
//!
//! Numbered files (`create_numbered`, through [`super::VcdTrace::create_numbered`]): each run writes a new file beside the name given,
//! `threads.vcd` giving `threads-1.vcd`, `threads-2.vcd`, … — the highest number is the
//! newest — so a service restarted by systemd never finds its file taken. The oldest are
//! removed so that the last `keep` remain; only regular files of this process's own (its
//! effective uid) bearing such a name are counted and removed: anything else there is
//! left alone.

use super::VcdError;
use std::fs::File;
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

/// The most files a numbered recording keeps.
pub const MAX_KEEP: u32 = 1000;

/// How many files a numbered recording keeps when not told.
pub const DEFAULT_KEEP: u32 = 10;

/// How many taken numbers are skipped before giving up (another process creating the same
/// names at once).
const TRIES: u64 = 100;

/// Creates `path` new for writing: never an existing name, never through a link, a
/// regular file.
pub(crate) fn create_new(path: &Path) -> Result<File, VcdError> {
    let error = |source| VcdError::Create {
        path: path.to_path_buf(),
        source,
    };
    let file = File::options()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.kind() == std::io::ErrorKind::AlreadyExists {
                let link = std::fs::symlink_metadata(path).is_ok_and(|m| m.is_symlink());
                error(std::io::Error::new(
                    e.kind(),
                    if link {
                        "is a symbolic link: refused (a recording is never written through a link)"
                    } else {
                        "exists: it is never overwritten"
                    },
                ))
            } else {
                error(e)
            }
        })?;
    let m = file.metadata().map_err(error)?;
    if !m.is_file() {
        return Err(error(std::io::Error::other("not a regular file: refused")));
    }
    Ok(file)
}

/// `base`'s numbered name: `threads.vcd` and 3 give `threads-3.vcd`; a name without an
/// extension gets the number at its end (`threads-3`).
pub fn numbered(base: &Path, n: u64) -> PathBuf {
    let (stem, ext) = parts(base);
    base.with_file_name(format!("{stem}-{n}{ext}"))
}

/// The stem and the extension (with its dot, or empty) of `base`'s file name.
fn parts(base: &Path) -> (String, String) {
    let stem = base
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let ext = base
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    (stem, ext)
}

/// The number in `name` if it is one of `base`'s numbered names.
fn number_of(name: &str, stem: &str, ext: &str) -> Option<u64> {
    let digits = name
        .strip_prefix(stem)?
        .strip_prefix('-')?
        .strip_suffix(ext)?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) || digits.starts_with('0') {
        return None;
    }
    digits.parse().ok()
}

/// `base`'s numbered files in its folder: (number, path, whether it is a regular file of
/// this process's own), in no order.
fn existing(base: &Path) -> std::io::Result<Vec<(u64, PathBuf, bool)>> {
    let (stem, ext) = parts(base);
    let dir = match base.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let uid = nix::unistd::geteuid().as_raw();
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name();
        let Some(n) = name.to_str().and_then(|s| number_of(s, &stem, &ext)) else {
            continue;
        };
        let path = base.with_file_name(&name);
        // Not followed: a link is not a file of ours.
        let own = std::fs::symlink_metadata(&path)
            .is_ok_and(|m| m.file_type().is_file() && m.uid() == uid);
        out.push((n, path, own));
    }
    Ok(out)
}

/// Creates the next numbered file of `base` (one past the highest of its own there), then
/// removes the oldest of this process's own numbered files beyond `keep` (the new one
/// counted; `keep` is at least 1). The file and its path.
pub(crate) fn create_numbered(base: &Path, keep: u32) -> Result<(File, PathBuf), VcdError> {
    let error = |source| VcdError::Create {
        path: base.to_path_buf(),
        source,
    };
    let found = existing(base).map_err(error)?;
    // Counted from this process's own files: a name another user planted (the highest
    // number there is) neither sets the next number nor is removed; one in the way is
    // passed over by the retries below.
    let mut n = found.iter().filter(|f| f.2).map(|f| f.0).max().unwrap_or(0);
    let mut made = None;
    for _ in 0..TRIES {
        n = n
            .checked_add(1)
            .ok_or_else(|| error(std::io::Error::other("no number left")))?;
        let path = numbered(base, n);
        match create_new(&path) {
            Ok(f) => {
                made = Some((f, path));
                break;
            }
            // Taken meanwhile (another process at the same names): the next one.
            Err(VcdError::Create { source, .. })
                if source.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
    }
    let (file, path) = made.ok_or_else(|| {
        error(std::io::Error::other(format!(
            "{TRIES} numbered names in a row were taken meanwhile"
        )))
    })?;
    let mut own: Vec<(u64, PathBuf)> = found
        .into_iter()
        .filter(|f| f.2)
        .map(|(n, p, _)| (n, p))
        .collect();
    own.sort_unstable_by_key(|f| std::cmp::Reverse(f.0));
    // The new file is the newest: `keep - 1` of the older ones stay.
    for (_, old) in own.iter().skip(keep.max(1) as usize - 1) {
        match std::fs::remove_file(old) {
            Ok(()) => tracing::info!("ThreadScope: removed the old recording {}", old.display()),
            Err(e) => tracing::warn!(
                "ThreadScope: cannot remove the old recording {}: {e}",
                old.display()
            ),
        }
    }
    Ok((file, path))
}

#[cfg(test)]
mod tests {
    #![allow(
        clippy::unwrap_used,
        reason = "test code: a failed unwrap is a failed test"
    )]

    use super::*;

    #[test]
    fn names_are_numbered_before_the_extension() {
        assert_eq!(
            numbered(Path::new("/var/log/threads.vcd"), 3),
            Path::new("/var/log/threads-3.vcd")
        );
        assert_eq!(numbered(Path::new("scope"), 12), Path::new("scope-12"));
        assert_eq!(numbered(Path::new("a.b.vcd"), 1), Path::new("a.b-1.vcd"));
        assert_eq!(number_of("threads-3.vcd", "threads", ".vcd"), Some(3));
        for other in [
            "threads.vcd",
            "threads-.vcd",
            "threads-03.vcd",
            "threads-3.vcd.bak",
        ] {
            assert_eq!(number_of(other, "threads", ".vcd"), None, "{other}");
        }
        assert_eq!(number_of("threads-x3.vcd", "threads", ".vcd"), None);
    }
}
