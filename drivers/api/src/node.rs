//! What a device path leads to, from `stat` alone: nothing is opened (opening a serial
//! port raises DTR and resets an Arduino, opening a watchdog arms it), so `hwgw check` can
//! refuse a path of the wrong kind before `run` would open it.
//!
//! ```
//! use driver_api::node::Node;
//!
//! let null = Node::of("/dev/null".as_ref())?;
//! assert_eq!(null, Node::Char { major: 1, minor: 3 });
//! assert_eq!(null.to_string(), "character device 1:3");
//! assert_eq!(Node::of("/".as_ref())?, Node::Dir);
//! # Ok::<(), std::io::Error>(())
//! ```

use std::fmt;
use std::path::Path;

/// The major and minor numbers of a device number (`st_rdev`), as glibc's `major()` and
/// `minor()` split it.
pub fn split_dev(rdev: u64) -> (u64, u64) {
    let major = ((rdev >> 8) & 0xfff) | ((rdev >> 32) & 0xffff_f000);
    let minor = (rdev & 0xff) | ((rdev >> 12) & 0xffff_ff00);
    (major, minor)
}

/// The kind of file a path leads to (links followed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Node {
    /// A character device.
    Char {
        /// Its major number (the driver).
        major: u64,
        /// Its minor number (the device of that driver).
        minor: u64,
    },
    /// A block device.
    Block {
        /// Its major number.
        major: u64,
        /// Its minor number.
        minor: u64,
    },
    /// A regular file.
    File,
    /// A directory.
    Dir,
    /// A FIFO or a socket.
    Other,
}

impl Node {
    /// What `path` leads to, following links; the error of `stat` (`NotFound` for a path
    /// that leads nowhere).
    pub fn of(path: &Path) -> std::io::Result<Node> {
        use std::os::unix::fs::{FileTypeExt, MetadataExt};
        let m = std::fs::metadata(path)?;
        let t = m.file_type();
        let (major, minor) = split_dev(m.rdev());
        Ok(if t.is_char_device() {
            Node::Char { major, minor }
        } else if t.is_block_device() {
            Node::Block { major, minor }
        } else if t.is_file() {
            Node::File
        } else if t.is_dir() {
            Node::Dir
        } else {
            Node::Other
        })
    }
}

impl Node {
    /// Why a file of this kind can never be a serial line, or `None` when it may be one:
    /// anything but a character device, a memory device (major 1: `/dev/null`,
    /// `/dev/mem`), a virtual console (4:0-63, `/dev/tty0`…), `/dev/tty` (5:0) and
    /// `/dev/console` (5:1). For a serial port's path at check, from `stat` alone: opening
    /// a port raises DTR, which resets an Arduino.
    pub fn never_serial(self) -> Option<String> {
        match self {
            Node::Char { major: 1, minor } => Some(format!(
                "it is a memory device (1:{minor}, as /dev/null and /dev/mem are)"
            )),
            Node::Char { major: 4, minor } if minor < 64 => Some(format!(
                "it is a virtual console (4:{minor}, /dev/tty{minor})"
            )),
            Node::Char { major: 5, minor: 0 } => {
                Some("it is /dev/tty, the controlling terminal (5:0)".into())
            }
            Node::Char { major: 5, minor: 1 } => {
                Some("it is /dev/console, the system console (5:1)".into())
            }
            Node::Char { .. } => None,
            other => Some(format!("it is {other}, not a character device")),
        }
    }
}

impl fmt::Display for Node {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Node::Char { major, minor } => write!(f, "character device {major}:{minor}"),
            Node::Block { major, minor } => write!(f, "block device {major}:{minor}"),
            Node::File => f.write_str("a regular file"),
            Node::Dir => f.write_str("a directory"),
            Node::Other => f.write_str("a FIFO or socket"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn what_can_never_be_a_serial_line() {
        for (node, why) in [
            (
                Node::Char { major: 4, minor: 1 },
                Some("it is a virtual console (4:1, /dev/tty1)"),
            ),
            (
                Node::Char {
                    major: 4,
                    minor: 63,
                },
                Some("it is a virtual console (4:63, /dev/tty63)"),
            ),
            (
                Node::Char { major: 5, minor: 0 },
                Some("it is /dev/tty, the controlling terminal (5:0)"),
            ),
            (
                Node::Char { major: 5, minor: 1 },
                Some("it is /dev/console, the system console (5:1)"),
            ),
            (
                Node::Char { major: 1, minor: 3 },
                Some("it is a memory device (1:3, as /dev/null and /dev/mem are)"),
            ),
            (
                Node::Block { major: 8, minor: 0 },
                Some("it is block device 8:0, not a character device"),
            ),
            (
                Node::File,
                Some("it is a regular file, not a character device"),
            ),
            // ttyS0, ttyUSB0, ttyACM0, a pty: may be serial lines.
            (
                Node::Char {
                    major: 4,
                    minor: 64,
                },
                None,
            ),
            (
                Node::Char {
                    major: 188,
                    minor: 0,
                },
                None,
            ),
            (
                Node::Char {
                    major: 166,
                    minor: 0,
                },
                None,
            ),
            (
                Node::Char {
                    major: 136,
                    minor: 3,
                },
                None,
            ),
        ] {
            assert_eq!(node.never_serial().as_deref(), why, "{node:?}");
        }
    }

    #[test]
    fn device_numbers_split_as_glibc_does() {
        assert_eq!(split_dev(0x0103), (1, 3));
        assert_eq!(split_dev(0x0501), (5, 1));
        // A minor above 255 and a major above 4095 take the high bits (glibc's makedev).
        let makedev = |major: u64, minor: u64| {
            ((major & 0xfff) << 8)
                | ((major & !0xfff) << 32)
                | (minor & 0xff)
                | ((minor & !0xff) << 12)
        };
        for (major, minor) in [(89, 0), (4, 63), (0x1234, 0x1ab), (511, 1_048_575)] {
            assert_eq!(split_dev(makedev(major, minor)), (major, minor));
        }
    }
}
