//! A socket's directory held open: created if missing (never over an existing one), opened
//! without following a link, checked through its descriptor (this user's or root's,
//! writable by no one else), and from then on the only way the socket is looked at,
//! replaced, bound and removed — by name relative to that descriptor, so a directory
//! renamed or swapped above it cannot redirect a step to another file.

use super::{SocketError, io};
use nix::errno::Errno;
use nix::fcntl::{AtFlags, OFlag};
use nix::sys::stat::{FileStat, Mode, SFlag};
use nix::unistd::{Gid, Uid};
use std::ffi::{OsStr, OsString};
use std::os::fd::{AsRawFd, OwnedFd};
use std::os::unix::fs::DirBuilderExt;
use std::os::unix::net::UnixListener;
use std::path::{Path, PathBuf};

/// `path` as its directory (`.` when it has none) and file name.
pub(super) fn split(path: &Path) -> Result<(PathBuf, OsString), SocketError> {
    let name = path.file_name().ok_or_else(|| SocketError::NoName {
        path: path.to_path_buf(),
    })?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    Ok((dir, name.to_os_string()))
}

fn nix_io(path: &Path) -> impl FnOnce(Errno) -> SocketError + '_ {
    move |e| io(path)(std::io::Error::from(e))
}

/// An open, checked socket directory.
pub(super) struct SocketDir {
    fd: OwnedFd,
    path: PathBuf,
}

impl SocketDir {
    /// Opens `dir` (creating it, with `create`, mode 0750 group `hwgw` for the `service`'s
    /// socket, else 0700) and checks it.
    pub(super) fn open(dir: &Path, service: bool, create: bool) -> Result<SocketDir, SocketError> {
        if create {
            if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
                std::fs::create_dir_all(parent).map_err(io(parent))?;
            }
            let mode = if service { 0o750 } else { 0o700 };
            // Not recursive: a directory someone made first is checked, never adopted.
            match std::fs::DirBuilder::new().mode(mode).create(dir) {
                Ok(()) => {
                    if service && let Some(gid) = super::service_gid() {
                        let _ = nix::unistd::chown(dir, None, Some(gid));
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(io(dir)(e)),
            }
        }
        let flags = OFlag::O_DIRECTORY | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC | OFlag::O_RDONLY;
        let fd = nix::fcntl::open(dir, flags, Mode::empty()).map_err(|e| match e {
            Errno::ELOOP | Errno::ENOTDIR if is_link(dir) => SocketError::LinkedDirectory {
                dir: dir.to_path_buf(),
            },
            e => nix_io(dir)(e),
        })?;
        let st = nix::sys::stat::fstat(&fd).map_err(nix_io(dir))?;
        let me = Uid::effective().as_raw();
        // Nobody else may write: no group or other write bit.
        if !(st.st_uid == me || st.st_uid == 0) || st.st_mode & 0o022 != 0 {
            return Err(SocketError::UnsafeDirectory {
                dir: dir.to_path_buf(),
                owner: st.st_uid,
                mode: st.st_mode & 0o7777,
            });
        }
        Ok(SocketDir {
            fd,
            path: dir.to_path_buf(),
        })
    }

    fn at(&self, name: &OsStr) -> PathBuf {
        self.path.join(name)
    }

    /// The socket named `name`, if any; an error when something that is not a socket is
    /// there.
    pub(super) fn existing(&self, name: &OsStr) -> Result<Option<FileStat>, SocketError> {
        match nix::sys::stat::fstatat(&self.fd, name, AtFlags::AT_SYMLINK_NOFOLLOW) {
            Err(Errno::ENOENT) => Ok(None),
            Err(e) => Err(nix_io(&self.at(name))(e)),
            Ok(st) if SFlag::from_bits_truncate(st.st_mode) & SFlag::S_IFMT == SFlag::S_IFSOCK => {
                Ok(Some(st))
            }
            Ok(_) => Err(SocketError::NotASocket {
                path: self.at(name),
            }),
        }
    }

    /// Removes the socket `name` (this user's, `path` for messages) if no server answers
    /// on it: only a refused connection proves it stale. A live server, even one too busy
    /// to accept, keeps it; any other answer is an error and the file stays.
    pub(super) fn remove_stale(&self, name: &OsStr, path: &Path) -> Result<(), SocketError> {
        use nix::sys::socket::{AddressFamily, SockFlag, SockType, UnixAddr, connect, socket};
        let probe = socket(
            AddressFamily::Unix,
            SockType::Stream,
            SockFlag::SOCK_NONBLOCK | SockFlag::SOCK_CLOEXEC,
            None,
        )
        .map_err(nix_io(path))?;
        let addr = UnixAddr::new(&self.through(name)).map_err(nix_io(path))?;
        match connect(probe.as_raw_fd(), &addr) {
            Err(Errno::ECONNREFUSED) => {}
            Ok(()) | Err(Errno::EAGAIN | Errno::EINPROGRESS) => {
                return Err(SocketError::InUse {
                    path: path.to_path_buf(),
                });
            }
            Err(e) => return Err(nix_io(path)(e)),
        }
        nix::unistd::unlinkat(&self.fd, name, nix::unistd::UnlinkatFlags::NoRemoveDir)
            .map_err(nix_io(path))
    }

    /// A path to `name` that resolves through this directory's descriptor
    /// (`/proc/self/fd/N/name`), or its plain path where `/proc` is not mounted.
    fn through(&self, name: &OsStr) -> PathBuf {
        let proc = PathBuf::from(format!("/proc/self/fd/{}", self.fd.as_raw_fd()));
        if proc.is_dir() {
            proc.join(name)
        } else {
            self.at(name)
        }
    }

    /// Binds `name` with `mode` (through the umask: never a moment with more access),
    /// group `gid` if given. Returns the listener and the socket's (device, inode).
    pub(super) fn bind(
        &self,
        name: &OsStr,
        mode: u32,
        gid: Option<Gid>,
    ) -> Result<(UnixListener, (u64, u64)), SocketError> {
        let path = self.at(name);
        let old = nix::sys::stat::umask(Mode::from_bits_truncate(0o777 & !mode));
        let bound = UnixListener::bind(self.through(name));
        nix::sys::stat::umask(old);
        let listener = bound.map_err(io(&path))?;
        let nofollow = AtFlags::AT_SYMLINK_NOFOLLOW;
        if let Some(gid) = gid {
            let _ = nix::unistd::fchownat(&self.fd, name, None, Some(gid), nofollow);
        }
        let st = nix::sys::stat::fstatat(&self.fd, name, nofollow).map_err(nix_io(&path))?;
        Ok((listener, (st.st_dev, st.st_ino)))
    }

    /// Removes `name` if it is still the socket `id` (device, inode).
    pub(super) fn remove_if(&self, name: &OsStr, id: (u64, u64)) {
        if let Ok(st) = nix::sys::stat::fstatat(&self.fd, name, AtFlags::AT_SYMLINK_NOFOLLOW)
            && (st.st_dev, st.st_ino) == id
        {
            let _ = nix::unistd::unlinkat(&self.fd, name, nix::unistd::UnlinkatFlags::NoRemoveDir);
        }
    }
}

fn is_link(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink())
}
