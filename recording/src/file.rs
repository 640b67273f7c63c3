//! Files hwgw writes, opened so that a path cannot be turned against the process: never
//! through a symbolic link (`O_NOFOLLOW`), never anything but a regular file (checked with
//! `fstat` on the descriptor just opened, so nothing can be swapped in between), and
//! never another's file:
//!
//! - [`create_new`]: a file made new (`O_EXCL`) — a recording, a picture: an existing
//!   name, a link included, is refused;
//! - [`replace_own`]: a file rewritten at each start (a report): created when missing,
//!   and when it exists, truncated only if it is this process's own (its owner is the
//!   effective uid) and has no other name (one hard link) — so a file planted under the
//!   name, or a link to someone else's file, is refused and left as it was.
//!
//! [`check_replace_own`] says beforehand, without opening or changing anything, whether
//! [`replace_own`] would refuse an existing file (for `hwgw check`).

use std::fs::{File, Metadata, OpenOptions};
use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

/// Why a file was not opened for writing.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {why}", path = path.display())]
pub struct FileError {
    /// The file.
    pub path: PathBuf,
    /// Why.
    pub why: Refusal,
}

/// What was wrong with a file hwgw was to write.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Refusal {
    /// A new file was meant and the name exists.
    #[error("exists: it is never overwritten; remove it or name another file")]
    Exists,
    /// The name is a symbolic link.
    #[error("is a symbolic link: refused (hwgw never writes through a link)")]
    Link,
    /// The name is a folder, a FIFO, a device or a socket.
    #[error("is a {0}, not a regular file: refused")]
    NotRegular(&'static str),
    /// The file belongs to another user.
    #[error(
        "belongs to uid {owner}, not to this process (uid {uid}): refused, another's file is never replaced"
    )]
    NotOwned {
        /// The file's owner.
        owner: u32,
        /// This process's effective uid.
        uid: u32,
    },
    /// The file has other names.
    #[error(
        "has {0} hard links: refused (replacing it would change the file under its other names too)"
    )]
    Linked(u64),
    /// The system refused (no such folder, permission, no space, …).
    #[error("{}", describe(.0))]
    Io(std::io::Error),
}

/// An I/O error for people: a full disk named as such (`ENOSPC`), others as the system
/// says them.
pub fn describe(e: &std::io::Error) -> String {
    match e.raw_os_error() {
        Some(nix::libc::ENOSPC) => "no space left on device (ENOSPC)".into(),
        Some(nix::libc::EDQUOT) => "disk quota exceeded (EDQUOT)".into(),
        _ => e.to_string(),
    }
}

fn fail(path: &Path, why: Refusal) -> FileError {
    FileError {
        path: path.to_path_buf(),
        why,
    }
}

/// What kind of thing other than a regular file `m` describes.
fn kind(m: &Metadata) -> &'static str {
    let t = m.file_type();
    if t.is_dir() {
        "folder"
    } else if t.is_symlink() {
        "symbolic link"
    } else if t.is_fifo() {
        "FIFO"
    } else if t.is_socket() {
        "socket"
    } else if t.is_char_device() {
        "character device"
    } else if t.is_block_device() {
        "block device"
    } else {
        "special file"
    }
}

/// Whether an existing file (its `fstat` or `lstat`) may be replaced by this process.
fn may_replace(m: &Metadata) -> Result<(), Refusal> {
    if m.file_type().is_symlink() {
        return Err(Refusal::Link);
    }
    if !m.is_file() {
        return Err(Refusal::NotRegular(kind(m)));
    }
    let uid = nix::unistd::geteuid().as_raw();
    if m.uid() != uid {
        return Err(Refusal::NotOwned {
            owner: m.uid(),
            uid,
        });
    }
    if m.nlink() > 1 {
        return Err(Refusal::Linked(m.nlink()));
    }
    Ok(())
}

/// Creates `path` new for writing: `O_CREAT | O_EXCL | O_NOFOLLOW`, so an existing name —
/// a file, a link, anything — is refused and left untouched.
pub fn create_new(path: &Path) -> Result<File, FileError> {
    let file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(nix::libc::O_NOFOLLOW | nix::libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.kind() == std::io::ErrorKind::AlreadyExists {
                // Only to say which: refused either way.
                let link =
                    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
                fail(path, if link { Refusal::Link } else { Refusal::Exists })
            } else {
                fail(path, Refusal::Io(e))
            }
        })?;
    let m = file.metadata().map_err(|e| fail(path, Refusal::Io(e)))?;
    if !m.is_file() {
        return Err(fail(path, Refusal::NotRegular(kind(&m))));
    }
    Ok(file)
}

/// Opens `path` to be rewritten from its start: created when missing; an existing file
/// is truncated only when [`check_replace_own`] allows it, checked again on the open
/// descriptor. A link is never followed, and a FIFO or a device is refused before it is
/// opened when it can be seen (and after, by the check on the descriptor, when one was
/// swapped in meanwhile: opened without blocking, never written).
pub fn replace_own(path: &Path) -> Result<File, FileError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) => may_replace(&m).map_err(|why| fail(path, why))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(fail(path, Refusal::Io(e))),
    }
    let file = OpenOptions::new()
        .write(true)
        .create(true)
        .custom_flags(nix::libc::O_NOFOLLOW | nix::libc::O_NONBLOCK | nix::libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.raw_os_error() == Some(nix::libc::ELOOP) {
                fail(path, Refusal::Link)
            } else {
                fail(path, Refusal::Io(e))
            }
        })?;
    let m = file.metadata().map_err(|e| fail(path, Refusal::Io(e)))?;
    may_replace(&m).map_err(|why| fail(path, why))?;
    file.set_len(0).map_err(|e| fail(path, Refusal::Io(e)))?;
    Ok(file)
}

/// Whether [`replace_own`] would take `path` as it is now, without opening or changing
/// it: `Ok(false)` when it does not exist (whether it can be created is the caller's
/// question), `Ok(true)` for a file of this process's it may write.
pub fn check_replace_own(path: &Path) -> Result<bool, FileError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) => {
            may_replace(&m).map_err(|why| fail(path, why))?;
            nix::unistd::access(path, nix::unistd::AccessFlags::W_OK)
                .map_err(|e| fail(path, Refusal::Io(e.into())))?;
            Ok(true)
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(fail(path, Refusal::Io(e))),
    }
}

#[cfg(test)]
mod tests {
    #![allow(
        clippy::unwrap_used,
        reason = "test code: a failed unwrap is a failed test"
    )]

    use super::*;
    use std::io::Write;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("hwgw-file-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_link_is_refused_and_its_target_untouched() {
        let d = dir("link");
        let target = d.join("precious");
        std::fs::write(&target, "keep me").unwrap();
        let link = d.join("out");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let e = create_new(&link).unwrap_err();
        assert!(matches!(e.why, Refusal::Link), "{e}");
        assert!(e.to_string().contains("out: is a symbolic link"), "{e}");
        let e = replace_own(&link).unwrap_err();
        assert!(matches!(e.why, Refusal::Link), "{e}");
        assert!(check_replace_own(&link).is_err());
        // A dangling link is not created through either.
        let dangling = d.join("dangling");
        std::os::unix::fs::symlink(d.join("made-through-the-link"), &dangling).unwrap();
        assert!(matches!(
            create_new(&dangling).unwrap_err().why,
            Refusal::Link
        ));
        assert!(matches!(
            replace_own(&dangling).unwrap_err().why,
            Refusal::Link
        ));
        assert!(!d.join("made-through-the-link").exists());
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "keep me");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn what_is_not_a_regular_file_is_refused() {
        let d = dir("special");
        let fifo = d.join("fifo");
        nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
        let e = replace_own(&fifo).unwrap_err();
        assert!(
            e.to_string().contains("is a FIFO, not a regular file"),
            "{e}"
        );
        assert!(matches!(
            create_new(&fifo).unwrap_err().why,
            Refusal::Exists
        ));
        let e = replace_own(&d).unwrap_err();
        assert!(e.to_string().contains("is a folder"), "{e}");
        let e = replace_own(Path::new("/dev/null")).unwrap_err();
        assert!(e.to_string().contains("character device"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_new_file_never_replaces_one_and_an_own_file_is_rewritten() {
        let d = dir("new");
        let f = d.join("a.csv");
        let mut file = create_new(&f).unwrap();
        file.write_all(b"first").unwrap();
        let e = create_new(&f).unwrap_err();
        assert!(
            e.to_string().contains("exists: it is never overwritten"),
            "{e}"
        );
        assert_eq!(std::fs::read_to_string(&f).unwrap(), "first");
        assert!(check_replace_own(&f).unwrap());
        let mut file = replace_own(&f).unwrap();
        file.write_all(b"second").unwrap();
        assert_eq!(std::fs::read_to_string(&f).unwrap(), "second");
        // Another name for the same file: replacing it would change both.
        std::fs::hard_link(&f, d.join("other-name")).unwrap();
        let e = replace_own(&f).unwrap_err();
        assert!(matches!(e.why, Refusal::Linked(2)), "{e}");
        assert_eq!(std::fs::read_to_string(&f).unwrap(), "second");
        assert!(!check_replace_own(&d.join("missing")).unwrap());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn another_users_file_is_never_truncated() {
        if !nix::unistd::geteuid().is_root() {
            // Only root can give a file away; the check is the same either way.
            return;
        }
        let d = dir("owner");
        let f = d.join("theirs");
        std::fs::write(&f, "theirs").unwrap();
        std::os::unix::fs::chown(&f, Some(65534), None).unwrap();
        let e = replace_own(&f).unwrap_err();
        assert!(
            matches!(e.why, Refusal::NotOwned { owner: 65534, .. }),
            "{e}"
        );
        assert!(e.to_string().contains("belongs to uid 65534"), "{e}");
        assert_eq!(std::fs::read_to_string(&f).unwrap(), "theirs");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_full_disk_is_named() {
        let e = std::io::Error::from_raw_os_error(nix::libc::ENOSPC);
        assert_eq!(describe(&e), "no space left on device (ENOSPC)");
    }
}
