//! Where the control socket lives, and handling it so that nothing a user types can harm
//! a file: a socket is only ever removed when it is a stale socket this user's hwgw made,
//! a per-user socket sits in a directory only that user can write, the service's socket is
//! `hwgw`'s group's, and a client talks only to a socket owned by itself, root or `hwgw`.
//!
//! | who | default path | mode |
//! |---|---|---|
//! | the service (systemd `RuntimeDirectory=hwgw`, or root) | `/run/hwgw/hwgw.sock` | 0660, group `hwgw` |
//! | a user | `$XDG_RUNTIME_DIR/hwgw.sock`, else `/tmp/hwgw-UID/hwgw.sock` (directory 0700) | 0600 |
//!
//! A client (the CLI, `hwgw browse`) looks for the user's own socket first, then the
//! service's.

use nix::unistd::{Gid, Group, Uid, User};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};

/// The service's socket.
pub const SERVICE_SOCKET: &str = "/run/hwgw/hwgw.sock";
/// The user and group the service runs as, and whose members may use its socket.
pub const SERVICE_GROUP: &str = "hwgw";

/// Why a socket path was refused.
#[derive(Debug, thiserror::Error)]
pub enum SocketError {
    /// Something that is not a socket is at the path: it is never replaced.
    #[error("{path}: exists and is not a socket; refusing to replace it (choose another --socket)")]
    NotASocket {
        /// The path.
        path: PathBuf,
    },
    /// A socket of another user is at the path.
    #[error("{path}: a socket of uid {owner}, not of this user (uid {me}); refusing to replace it")]
    NotOurs {
        /// The path.
        path: PathBuf,
        /// Its owner.
        owner: u32,
        /// This process's user.
        me: u32,
    },
    /// A live gateway serves the path.
    #[error("{path}: another hwgw is serving this socket")]
    InUse {
        /// The path.
        path: PathBuf,
    },
    /// The socket's directory is not safe: another user owns it or can write to it.
    #[error(
        "{dir}: owned by uid {owner} with mode {mode:o}; a socket directory must be this user's and writable by no one else"
    )]
    UnsafeDirectory {
        /// The directory.
        dir: PathBuf,
        /// Its owner.
        owner: u32,
        /// Its mode bits.
        mode: u32,
    },
    /// A client will not talk to a socket owned by someone else.
    #[error(
        "{path}: owned by uid {owner}, neither this user, root nor {SERVICE_GROUP}: not talking to it"
    )]
    Untrusted {
        /// The path.
        path: PathBuf,
        /// Its owner.
        owner: u32,
    },
    /// A file system call failed.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SocketError + '_ {
    move |source| SocketError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The service's directory from systemd (`RuntimeDirectory=`), if it set one.
fn runtime_directory() -> Option<PathBuf> {
    let dirs = std::env::var_os("RUNTIME_DIRECTORY")?;
    let first = dirs.to_string_lossy().split(':').next()?.to_string();
    (!first.is_empty()).then(|| PathBuf::from(first))
}

/// The user's own socket: `$XDG_RUNTIME_DIR/hwgw.sock`, else `/tmp/hwgw-UID/hwgw.sock`.
pub fn user_socket() -> PathBuf {
    match std::env::var_os("XDG_RUNTIME_DIR") {
        Some(dir) if !dir.is_empty() => Path::new(&dir).join("hwgw.sock"),
        _ => PathBuf::from(format!("/tmp/hwgw-{}/hwgw.sock", Uid::current())),
    }
}

/// Where `hwgw run` listens unless told: the systemd runtime directory, or
/// [`SERVICE_SOCKET`] as root, else the user's own socket.
pub fn default_server_socket() -> PathBuf {
    if let Some(dir) = runtime_directory() {
        return dir.join("hwgw.sock");
    }
    if Uid::effective().is_root() {
        return PathBuf::from(SERVICE_SOCKET);
    }
    user_socket()
}

/// Where a client looks unless told: `$HWGW_SOCKET`, the user's own socket if there is
/// one, else the service's.
pub fn default_client_socket() -> PathBuf {
    if let Some(p) = std::env::var_os("HWGW_SOCKET").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    let own = if Uid::effective().is_root() {
        PathBuf::from(SERVICE_SOCKET)
    } else {
        user_socket()
    };
    if own.exists() {
        own
    } else {
        PathBuf::from(SERVICE_SOCKET)
    }
}

/// The service group's id, if the group exists.
fn service_gid() -> Option<Gid> {
    Group::from_name(SERVICE_GROUP)
        .ok()
        .flatten()
        .map(|g| g.gid)
}

/// The service user's id, if the user exists.
fn service_uid() -> Option<Uid> {
    User::from_name(SERVICE_GROUP).ok().flatten().map(|u| u.uid)
}

/// True when `path` is the service's socket: in the systemd runtime directory or at
/// [`SERVICE_SOCKET`]; it is then shared with the service group.
fn is_service_path(path: &Path) -> bool {
    path == Path::new(SERVICE_SOCKET)
        || runtime_directory().is_some_and(|d| path.parent() == Some(d.as_path()))
}

/// A bound socket and how to recognise it when it is time to remove it.
pub struct Bound {
    /// The listener.
    pub listener: UnixListener,
    /// The path.
    pub path: PathBuf,
    /// (device, inode) of the socket file bound.
    id: (u64, u64),
}

impl Bound {
    /// Removes the socket file, if it is still the one bound here.
    pub fn remove(&self) {
        if let Ok(m) = std::fs::symlink_metadata(&self.path)
            && (m.dev(), m.ino()) == self.id
        {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// Makes sure `dir` exists and is safe for a socket: created with `mode` if missing; an
/// existing one must belong to this user (or root, for the service's) and be writable by
/// no one else.
fn prepare_dir(dir: &Path, mode: u32, service: bool) -> Result<(), SocketError> {
    if !dir.exists() {
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(mode)
            .create(dir)
            .map_err(io(dir))?;
        if service && let Some(gid) = service_gid() {
            let _ = nix::unistd::chown(dir, None, Some(gid));
        }
        return Ok(());
    }
    let m = std::fs::metadata(dir).map_err(io(dir))?;
    let me = Uid::effective().as_raw();
    let owner_ok = m.uid() == me || m.uid() == 0;
    // Nobody else may write: no group or other write bit, unless sticky (/tmp itself is
    // never the socket's directory here).
    let writable_by_others = m.mode() & 0o022 != 0;
    if !owner_ok || writable_by_others {
        return Err(SocketError::UnsafeDirectory {
            dir: dir.to_path_buf(),
            owner: m.uid(),
            mode: m.mode() & 0o7777,
        });
    }
    Ok(())
}

/// What `hwgw check` can tell about a socket path without touching it: nothing that is not
/// a socket at the path, no socket of a user other than this one or the service's (a
/// running service's socket is fine to find), and no unsafe directory above it.
pub fn check_path(path: &Path) -> Result<(), SocketError> {
    if let Some(dir) = path
        .parent()
        .filter(|d| d.exists() && !d.as_os_str().is_empty())
    {
        let service = is_service_path(path);
        prepare_dir(dir, if service { 0o750 } else { 0o700 }, service)?;
    }
    match existing_socket(path)? {
        Some(m) if service_uid().is_some_and(|u| u.as_raw() == m.uid()) => Ok(()),
        Some(m) => ours(path, &m),
        None => Ok(()),
    }
}

/// The metadata of the socket at `path`; `None` when nothing is there, an error when
/// something that is not a socket is.
fn existing_socket(path: &Path) -> Result<Option<std::fs::Metadata>, SocketError> {
    use std::os::unix::fs::FileTypeExt;
    match std::fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(path)(e)),
        Ok(m) if m.file_type().is_socket() => Ok(Some(m)),
        Ok(_) => Err(SocketError::NotASocket {
            path: path.to_path_buf(),
        }),
    }
}

/// Refuses the socket at `path` (metadata `m`) unless this user owns it.
fn ours(path: &Path, m: &std::fs::Metadata) -> Result<(), SocketError> {
    let me = Uid::effective().as_raw();
    if m.uid() != me {
        return Err(SocketError::NotOurs {
            path: path.to_path_buf(),
            owner: m.uid(),
            me,
        });
    }
    Ok(())
}

/// What is at `path` now, if it may be bound: nothing, or a stale socket of this user's
/// (removed). Anything else is refused and left as it is.
fn clear_stale(path: &Path) -> Result<(), SocketError> {
    let Some(m) = existing_socket(path)? else {
        return Ok(());
    };
    ours(path, &m)?;
    if UnixStream::connect(path).is_ok() {
        return Err(SocketError::InUse {
            path: path.to_path_buf(),
        });
    }
    std::fs::remove_file(path).map_err(io(path))
}

/// Binds the control socket at `path` safely: its directory prepared (0700 for a user's,
/// 0750 group `hwgw` for the service's), nothing but a stale socket of this user's
/// replaced, the socket created with mode 0600 (0660, group `hwgw`, for the service's).
pub fn bind(path: &Path) -> Result<Bound, SocketError> {
    let service = is_service_path(path);
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        prepare_dir(dir, if service { 0o750 } else { 0o700 }, service)?;
    }
    clear_stale(path)?;
    // The socket gets its mode from the umask at bind: never a moment with more access.
    let mode = if service { 0o660 } else { 0o600 };
    let old = nix::sys::stat::umask(nix::sys::stat::Mode::from_bits_truncate(0o777 & !mode));
    let bound = UnixListener::bind(path);
    nix::sys::stat::umask(old);
    let listener = bound.map_err(io(path))?;
    if service && let Some(gid) = service_gid() {
        let _ = nix::unistd::chown(path, None, Some(gid));
    }
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).map_err(io(path))?;
    let m = std::fs::symlink_metadata(path).map_err(io(path))?;
    Ok(Bound {
        listener,
        path: path.to_path_buf(),
        id: (m.dev(), m.ino()),
    })
}

/// A client's check before it talks: the socket must belong to this user, root or the
/// service user (another user's socket could answer anything).
pub fn check_owner(path: &Path) -> Result<(), SocketError> {
    let m = match std::fs::metadata(path) {
        Ok(m) => m,
        // Connecting will say what is wrong.
        Err(_) => return Ok(()),
    };
    let owner = m.uid();
    let me = Uid::effective().as_raw();
    if owner == me || owner == 0 || service_uid().is_some_and(|u| u.as_raw() == owner) {
        Ok(())
    } else {
        Err(SocketError::Untrusted {
            path: path.to_path_buf(),
            owner,
        })
    }
}
