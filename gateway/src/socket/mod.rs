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

mod dir;

use nix::unistd::{Gid, Group, Uid, User};
use std::os::unix::fs::MetadataExt;
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
    /// The socket's directory is a symbolic link (it could be pointed anywhere).
    #[error("{dir}: a symbolic link; a socket directory must be a directory of its own")]
    LinkedDirectory {
        /// The directory.
        dir: PathBuf,
    },
    /// A client was pointed at something that is not a socket (a file, a directory).
    #[error("{path} is not a socket (it is {kind}): give the control socket of a running hwgw")]
    NotASocketToTalkTo {
        /// The path.
        path: PathBuf,
        /// What is there: "a regular file", "a directory", ….
        kind: &'static str,
    },
    /// The path has no file name to bind.
    #[error("{path}: not a file path (a socket needs a name in a directory)")]
    NoName {
        /// The path.
        path: PathBuf,
    },
    /// The server at the path answered as a user other than this one, root or `hwgw`.
    #[error(
        "{path}: served by uid {uid}, neither this user, root nor {SERVICE_GROUP}: not talking to it"
    )]
    UntrustedPeer {
        /// The path.
        path: PathBuf,
        /// The serving process's user.
        uid: u32,
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

/// What `hwgw check` can tell about a socket path without touching it: nothing that is not
/// a socket at the path, no socket of a user other than this one or the service's (a
/// running service's socket is fine to find), and no unsafe directory above it.
pub fn check_path(path: &Path) -> Result<(), SocketError> {
    let (dir, name) = dir::split(path)?;
    if !dir.exists() {
        return Ok(());
    }
    let dir = dir::SocketDir::open(&dir, is_service_path(path), false)?;
    match dir.existing(&name)? {
        Some(st) if service_uid().is_some_and(|u| u.as_raw() == st.st_uid) => Ok(()),
        Some(st) => ours(path, st.st_uid),
        None => Ok(()),
    }
}

/// Refuses a socket at `path` owned by `owner` unless that is this user.
fn ours(path: &Path, owner: u32) -> Result<(), SocketError> {
    let me = Uid::effective().as_raw();
    if owner != me {
        return Err(SocketError::NotOurs {
            path: path.to_path_buf(),
            owner,
            me,
        });
    }
    Ok(())
}

/// Binds the control socket at `path` safely: its directory prepared (0700 for a user's,
/// 0750 group `hwgw` for the service's) and opened without following links, nothing but a
/// stale socket of this user's replaced, the socket created with mode 0600 (0660, group
/// `hwgw`, for the service's). Every step after the directory's check goes through its
/// descriptor: renaming a directory above it cannot redirect one.
pub fn bind(path: &Path) -> Result<Bound, SocketError> {
    let service = is_service_path(path);
    let (dir, name) = dir::split(path)?;
    let dir = dir::SocketDir::open(&dir, service, true)?;
    if let Some(st) = dir.existing(&name)? {
        ours(path, st.st_uid)?;
        dir.remove_stale(&name, path)?;
    }
    let mode = if service { 0o660 } else { 0o600 };
    let (listener, id) = dir.bind(&name, mode, service.then(service_gid).flatten())?;
    Ok(Bound {
        listener,
        path: path.to_path_buf(),
        dir,
        name,
        id,
    })
}

/// A bound socket and how to recognise it when it is time to remove it.
pub struct Bound {
    /// The listener.
    pub listener: UnixListener,
    /// The path.
    pub path: PathBuf,
    dir: dir::SocketDir,
    name: std::ffi::OsString,
    /// (device, inode) of the socket file bound.
    id: (u64, u64),
}

impl Bound {
    /// Removes the socket file, if it is still the one bound here.
    pub fn remove(&self) {
        self.dir.remove_if(&self.name, self.id);
    }
}

/// A client's check before it talks: a socket is at the path (not a file: connecting to
/// one says only "connection refused"), and it belongs to this user, root or the service
/// user (another user's socket could answer anything).
pub fn check_owner(path: &Path) -> Result<(), SocketError> {
    use std::os::unix::fs::FileTypeExt;
    let m = match std::fs::metadata(path) {
        Ok(m) => m,
        // Connecting will say what is wrong.
        Err(_) => return Ok(()),
    };
    let t = m.file_type();
    if !t.is_socket() {
        let kind = if t.is_file() {
            "a regular file"
        } else if t.is_dir() {
            "a directory"
        } else if t.is_fifo() {
            "a FIFO"
        } else if t.is_char_device() || t.is_block_device() {
            "a device"
        } else {
            "something else"
        };
        return Err(SocketError::NotASocketToTalkTo {
            path: path.to_path_buf(),
            kind,
        });
    }
    let owner = m.uid();
    if trusted(owner) {
        Ok(())
    } else {
        Err(SocketError::Untrusted {
            path: path.to_path_buf(),
            owner,
        })
    }
}

/// True for the users a client talks to: itself, root and the service user.
fn trusted(uid: u32) -> bool {
    uid == Uid::effective().as_raw() || uid == 0 || service_uid().is_some_and(|u| u.as_raw() == uid)
}

/// A client's check once connected: the process serving `conn` (at `path`) runs as this
/// user, root or the service user — what the socket file's owner said before connecting
/// holds for the server actually reached (the file could have been swapped in between).
pub fn check_peer(path: &Path, conn: &UnixStream) -> Result<(), SocketError> {
    let cred = nix::sys::socket::getsockopt(conn, nix::sys::socket::sockopt::PeerCredentials)
        .map_err(|e| SocketError::Io {
            path: path.to_path_buf(),
            source: e.into(),
        })?;
    let uid = cred.uid();
    if trusted(uid) {
        Ok(())
    } else {
        Err(SocketError::UntrustedPeer {
            path: path.to_path_buf(),
            uid,
        })
    }
}
