//! The serial line under a Firmata card: what the bus side needs of it (non-blocking reads
//! and writes, a descriptor to wait on), the real port opened through tokio-serial's
//! builder as mio-serial's non-blocking stream, and writing a whole message.

use std::io::{self, Read, Write};
use std::os::fd::BorrowedFd;

/// An open serial line: non-blocking reads and writes, and the descriptor to wait on.
pub trait Line: Send {
    /// Reads what is there (`WouldBlock` when nothing).
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize>;
    /// Writes what it can (`WouldBlock` when the line's buffer is full).
    fn write(&mut self, data: &[u8]) -> io::Result<usize>;
    /// The descriptor that becomes readable.
    fn fd(&self) -> BorrowedFd<'_>;
}

impl Line for mio_serial::SerialStream {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        Read::read(self, buf)
    }
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        Write::write(self, data)
    }
    // mio-serial gives its descriptor only as a raw one.
    #[allow(
        unsafe_code,
        reason = "borrowing the stream's own descriptor for its lifetime"
    )]
    fn fd(&self) -> BorrowedFd<'_> {
        // SAFETY: the stream owns this descriptor and keeps it open while borrowed: the
        // borrow cannot outlive `&self`.
        unsafe { BorrowedFd::borrow_raw(std::os::fd::AsRawFd::as_raw_fd(self)) }
    }
}

/// Opens a line: the port's path and baud rate.
pub type Opener = Box<dyn FnMut(&str, u32) -> io::Result<Box<dyn Line>> + Send>;

/// Checks that `path` is a serial port before anything opens it: a character device whose
/// number a tty driver of kind `serial` or `pty:slave` owns (in `/proc/tty/drivers`). So a
/// port given wrong never opens `/dev/watchdog` (which would arm it), a console, a FIFO or
/// a file.
pub fn check_serial(path: &str) -> io::Result<()> {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    let meta = std::fs::metadata(path)?;
    let not = |what: String| io::Error::other(format!("{path} is not a serial port: {what}"));
    if !meta.file_type().is_char_device() {
        return Err(not("not a character device".into()));
    }
    let dev = meta.rdev();
    let major = ((dev >> 8) & 0xfff) | ((dev >> 32) & !0xfff);
    let minor = (dev & 0xff) | ((dev >> 12) & !0xff);
    let drivers = std::fs::read_to_string("/proc/tty/drivers").unwrap_or_default();
    let owner = drivers.lines().find_map(|l| {
        let f: Vec<&str> = l.split_whitespace().collect();
        let [name, _, maj, minors, kind] = f[..] else {
            return None;
        };
        let (lo, hi) = minors.split_once('-').unwrap_or((minors, minors));
        let inside = maj.parse() == Ok(major)
            && lo.parse::<u64>().is_ok_and(|lo| lo <= minor)
            && hi.parse::<u64>().is_ok_and(|hi| minor <= hi);
        inside.then(|| (name.to_string(), kind.to_string()))
    });
    match owner {
        Some((_, kind)) if kind == "serial" || kind == "pty:slave" => Ok(()),
        Some((name, kind)) => Err(not(format!(
            "device {major}:{minor} is the tty driver {name}'s ({kind})"
        ))),
        None => Err(not(format!(
            "no tty driver owns device {major}:{minor} (see /proc/tty/drivers)"
        ))),
    }
}

/// What `hwgw check` can tell of a port from `stat`, without opening it (opening one
/// raises DTR and resets an Arduino): nothing at the path yet is fine (a board unplugged
/// now is looked for again at run); anything there must be a character device that can
/// be a serial line ([`Node::never_serial`](driver_api::node::Node::never_serial): not a
/// memory device, a virtual console, `/dev/tty` or `/dev/console`) and, where
/// `/proc/tty/drivers` says, one that a serial tty driver owns ([`check_serial`], as
/// opening it checks).
pub fn check_port(path: &str) -> io::Result<()> {
    use driver_api::node::Node;
    let node = match Node::of(std::path::Path::new(path)) {
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(io::Error::new(e.kind(), format!("{path}: {e}"))),
        Ok(n) => n,
    };
    if let Some(what) = node.never_serial() {
        return Err(io::Error::other(format!(
            "{path} is not a serial port: {what}"
        )));
    }
    if std::path::Path::new("/proc/tty/drivers").exists() {
        check_serial(path)?;
    }
    Ok(())
}

/// Opens a real serial port (8N1, no flow control, exclusive: a second program cannot open
/// it while hwgw has it), once [`check_serial`] says it is one.
pub fn open_port(path: &str, baud: u32) -> io::Result<Box<dyn Line>> {
    check_serial(path)?;
    let builder = tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None);
    let stream = mio_serial::SerialStream::open(&builder).map_err(io::Error::from)?;
    Ok(Box::new(stream))
}

/// The device node a path leads to now (following links): its file system, inode, device
/// number and change time, or None when there is none. A board plugged back gets a node
/// made anew (a new change time, even where the inode and number are reused), and a stable
/// name pointed elsewhere leads to another node.
pub fn identity(path: &str) -> Option<(u64, u64, u64, i64)> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).ok()?;
    Some((
        m.dev(),
        m.ino(),
        m.rdev(),
        m.ctime()
            .saturating_mul(1_000_000_000)
            .saturating_add(m.ctime_nsec()),
    ))
}

/// Why [`send`] did not write everything.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// The port took no byte.
    #[error("write: the port took nothing")]
    TookNothing,
    /// The write failed (a line whose buffer stays full for a second: would block).
    #[error("write: {0}")]
    Io(#[from] io::Error),
}

/// The bus side's steps carry their errors as text to their component's log.
impl From<SendError> for String {
    fn from(e: SendError) -> String {
        e.to_string()
    }
}

/// Writes all of `data`, counting what went out in `sent`; a line whose buffer stays full
/// is stuck.
pub fn send(
    line: &mut dyn Line,
    data: &[u8],
    sent: &std::sync::atomic::AtomicU64,
) -> Result<(), SendError> {
    let mut rest = data;
    let mut waits = 0;
    while !rest.is_empty() {
        match line.write(rest) {
            Ok(0) => return Err(SendError::TookNothing),
            Ok(n) => {
                sent.fetch_add(n as u64, std::sync::atomic::Ordering::Relaxed);
                rest = &rest[n..];
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock && waits < 100 => {
                // The line's buffer is full (a slow baud rate): wait for room, 1 s at most.
                waits += 1;
                let fd = line.fd();
                let mut p = [nix::poll::PollFd::new(fd, nix::poll::PollFlags::POLLOUT)];
                let _ = nix::poll::poll(&mut p, nix::poll::PollTimeout::from(10u8));
            }
            Err(e) => return Err(SendError::Io(e)),
        }
    }
    Ok(())
}
