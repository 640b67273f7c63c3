//! A CAN_RAW socket as hwgw's CAN drivers use it: bound to one interface, FD-capable,
//! non-blocking, with kernel filters for exactly the ids wanted and every error class,
//! each frame received with the kernel's timestamp and the socket's drop count.
//!
//! [`check_interface`] says, before a socket is opened, whether an interface is there and
//! can carry what a driver maps, as an [`InterfaceError`] that lists the CAN interfaces
//! that exist.

use crate::link::{ARPHRD_CAN, can_interfaces, link, sys_u32};
use nix::sys::socket::{ControlMessageOwned, MsgFlags, recvmsg, setsockopt, sockopt};
use nix::sys::time::TimeSpec;
use socketcan::{CanFdSocket, CanFilter, EmbeddedFrame, Socket, SocketOptions};
use std::os::fd::{AsFd, AsRawFd, BorrowedFd};

/// Why an interface cannot carry a driver's frames.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InterfaceError {
    /// No network interface of that name.
    #[error("interface {name:?}: no such network interface (CAN interfaces here: {})", if .available.is_empty() { "none".to_string() } else { .available.join(", ") })]
    NoInterface {
        /// The name asked for.
        name: String,
        /// The CAN interfaces that exist.
        available: Vec<String>,
    },
    /// The interface is not a CAN interface.
    #[error("interface {0:?} is not a CAN interface")]
    NotCan(String),
    /// FD frames are mapped but the interface is classic CAN only.
    #[error("interface {name:?} is classic CAN (MTU {mtu}); frame {frame} is a CAN FD frame")]
    NoFd {
        /// The interface.
        name: String,
        /// Its MTU.
        mtu: u32,
        /// A frame that needs FD.
        frame: String,
    },
    /// A system call failed.
    #[error("interface {name:?}: {what}: {source}")]
    Os {
        /// The interface.
        name: String,
        /// What was being done.
        what: &'static str,
        /// The error.
        source: std::io::Error,
    },
}

/// Extended (29-bit) frame format flag of a `can_id`.
pub const CAN_EFF_FLAG: u32 = 0x8000_0000;
/// Remote transmission request flag.
pub const CAN_RTR_FLAG: u32 = 0x4000_0000;
/// Error frame flag.
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// Standard (11-bit) id mask.
pub const CAN_SFF_MASK: u32 = 0x7FF;
/// Extended (29-bit) id mask.
pub const CAN_EFF_MASK: u32 = 0x1FFF_FFFF;
/// Error class mask.
pub const CAN_ERR_MASK: u32 = 0x1FFF_FFFF;
/// Size of a classic `struct can_frame`.
pub const CAN_MTU: usize = 16;
/// Size of a `struct canfd_frame`.
pub const CANFD_MTU: usize = 72;

/// Interface `name`'s index, if it is a CAN interface that can carry what is mapped
/// (`fd_frame`: the name of a CAN FD frame the driver maps, if any). An interface that is
/// there but down is fine (a driver waits for it to come up).
pub fn check_interface(name: &str, fd_frame: Option<&str>) -> Result<u32, InterfaceError> {
    let Some((_, ifindex)) = link(name) else {
        return Err(InterfaceError::NoInterface {
            name: name.into(),
            available: can_interfaces(),
        });
    };
    if sys_u32(name, "type") != Some(ARPHRD_CAN) {
        return Err(InterfaceError::NotCan(name.into()));
    }
    let mtu = sys_u32(name, "mtu").unwrap_or(0);
    if let Some(frame) = fd_frame
        && mtu as usize != CANFD_MTU
    {
        return Err(InterfaceError::NoFd {
            name: name.into(),
            mtu,
            frame: frame.into(),
        });
    }
    Ok(ifindex)
}

/// The ids a socket receives: one exact id, standard or extended, or a standard id under a
/// mask (CANopen's function codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Filter {
    /// The id.
    pub id: u32,
    /// Extended (29-bit) id.
    pub extended: bool,
    /// The id bits that must match (11 or 29 bits set for an exact id).
    pub mask: u32,
}

impl Filter {
    /// Exactly `id`.
    pub fn exact(id: u32, extended: bool) -> Filter {
        let mask = if extended { CAN_EFF_MASK } else { CAN_SFF_MASK };
        Filter { id, extended, mask }
    }
}

/// One received frame, its payload in the caller's buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// A data frame.
    Data {
        /// Its id (without flags).
        id: u32,
        /// Extended id.
        extended: bool,
        /// A CAN FD frame.
        fd: bool,
        /// Payload length.
        len: usize,
    },
    /// An error frame: its error class bits, `len` bytes of data.
    Error {
        /// The class bits.
        class: u32,
        /// Payload length.
        len: usize,
    },
    /// A remote frame, or a read of neither size: not a data frame.
    WrongKind,
}

/// A received frame, when the kernel stamped it (CLOCK_REALTIME, ns), and how many frames
/// the socket dropped since the last receive reported some.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Received {
    /// The frame.
    pub frame: Frame,
    /// The kernel's receive time, CLOCK_REALTIME ns.
    pub stamp: Option<i128>,
    /// Frames the socket dropped (its buffer full) since the last report.
    pub dropped: u32,
}

/// A CAN_RAW socket bound to one interface: non-blocking, unless its reader waits in it
/// (see [`crate::blocking`]); its sends never wait either way.
pub struct RawSocket {
    socket: CanFdSocket,
    /// Room for the timestamp and drop-count control messages (allocated once).
    cmsg: Vec<u8>,
    /// The kernel's drop counter as last seen.
    drops_seen: u32,
}

impl RawSocket {
    /// Opens a socket on `interface` receiving `filters` (none: no data frames) and every
    /// error class.
    pub fn open(interface: &str, filters: &[Filter]) -> std::io::Result<RawSocket> {
        let s = CanFdSocket::open(interface)?;
        let filters: Vec<CanFilter> = filters
            .iter()
            .map(|f| {
                if f.extended {
                    CanFilter::new(f.id | CAN_EFF_FLAG, f.mask | CAN_EFF_FLAG | CAN_RTR_FLAG)
                } else {
                    CanFilter::new(f.id, f.mask | CAN_EFF_FLAG | CAN_RTR_FLAG)
                }
            })
            .collect();
        s.set_filters(&filters)?;
        s.set_error_filter(CAN_ERR_MASK)?;
        s.set_nonblocking(true)?;
        setsockopt(&s, sockopt::ReceiveTimestampns, &true).map_err(std::io::Error::from)?;
        setsockopt(&s, sockopt::RxqOvfl, &1).map_err(std::io::Error::from)?;
        Ok(RawSocket {
            socket: s,
            cmsg: nix::cmsg_space!(TimeSpec, u32),
            drops_seen: 0,
        })
    }

    /// Receives one queued frame into `data` without blocking: None when none is queued
    /// (EINTR is retried). The error is the socket's (ENETDOWN or ENODEV when the link went).
    pub fn recv(&mut self, data: &mut [u8; 64]) -> nix::Result<Option<Received>> {
        let mut raw = [0u8; CANFD_MTU];
        let fd = self.socket.as_raw_fd();
        let (n, stamp, drops) = loop {
            let mut iov = [std::io::IoSliceMut::new(&mut raw)];
            match recvmsg::<()>(fd, &mut iov, Some(&mut self.cmsg), MsgFlags::MSG_DONTWAIT) {
                Ok(msg) => {
                    let mut stamp = None;
                    let mut drops = None;
                    if let Ok(cmsgs) = msg.cmsgs() {
                        for c in cmsgs {
                            match c {
                                ControlMessageOwned::ScmTimestampns(t) => {
                                    stamp = Some(
                                        t.tv_sec() as i128 * 1_000_000_000 + t.tv_nsec() as i128,
                                    )
                                }
                                ControlMessageOwned::RxqOvfl(d) => drops = Some(d),
                                _ => {}
                            }
                        }
                    }
                    break (msg.bytes, stamp, drops);
                }
                Err(nix::Error::EAGAIN) => return Ok(None),
                Err(nix::Error::EINTR) => continue,
                Err(e) => return Err(e),
            }
        };
        let dropped = self.dropped_since(drops);
        Ok(Some(Received {
            frame: frame_of(&raw, n, data),
            stamp,
            dropped,
        }))
    }

    /// The frames dropped since the last report, from a received drop counter.
    pub(crate) fn dropped_since(&mut self, drops: Option<u32>) -> u32 {
        let Some(d) = drops else { return 0 };
        let dropped = d.wrapping_sub(self.drops_seen);
        self.drops_seen = d;
        dropped
    }

    /// Sends one frame (a classic frame carries at most 8 bytes, an FD frame 64). An id
    /// or length the frame format cannot carry is InvalidInput.
    pub fn send(&self, id: u32, extended: bool, fd: bool, data: &[u8]) -> std::io::Result<()> {
        let invalid = || std::io::Error::from(std::io::ErrorKind::InvalidInput);
        let id: socketcan::Id = if extended {
            socketcan::ExtendedId::new(id).ok_or_else(invalid)?.into()
        } else {
            u16::try_from(id)
                .ok()
                .and_then(socketcan::StandardId::new)
                .ok_or_else(invalid)?
                .into()
        };
        if fd {
            let frame = socketcan::CanFdFrame::new(id, data).ok_or_else(invalid)?;
            self.send_bytes(&frame)
        } else {
            let frame = socketcan::CanFrame::new(id, data).ok_or_else(invalid)?;
            self.send_bytes(&frame)
        }
    }

    /// Sends `frame` without ever waiting (the socket may be blocking for its reader):
    /// a full queue is an error (ENOBUFS or EAGAIN), as on a non-blocking socket.
    fn send_bytes(&self, frame: &impl socketcan::frame::AsPtr) -> std::io::Result<()> {
        #[allow(
            unsafe_code,
            reason = "the frame's bytes as the kernel takes them; socketcan's own write reads them so"
        )]
        // SAFETY: socketcan's frames start from a zeroed struct and zero what a shorter
        // payload leaves (its `AsPtr::as_bytes` contract), so every byte is initialised.
        let bytes = unsafe { frame.as_bytes() };
        let n = nix::sys::socket::send(self.socket.as_raw_fd(), bytes, MsgFlags::MSG_DONTWAIT)
            .map_err(std::io::Error::from)?;
        if n == bytes.len() {
            Ok(())
        } else {
            Err(std::io::Error::from(std::io::ErrorKind::WriteZero))
        }
    }
}

/// The frame in `raw`, `n` bytes as the kernel gave them (a `can_frame` or
/// `canfd_frame`), its payload copied into `data`.
pub(crate) fn frame_of(raw: &[u8; CANFD_MTU], n: usize, data: &mut [u8; 64]) -> Frame {
    if n != CAN_MTU && n != CANFD_MTU {
        return Frame::WrongKind;
    }
    let can_id = u32::from_ne_bytes([raw[0], raw[1], raw[2], raw[3]]);
    let len = usize::from(raw[4]).min(if n == CAN_MTU { 8 } else { 64 });
    data[..len].copy_from_slice(&raw[8..8 + len]);
    let extended = can_id & CAN_EFF_FLAG != 0;
    if can_id & CAN_ERR_FLAG != 0 {
        Frame::Error {
            class: can_id & CAN_ERR_MASK,
            len,
        }
    } else if can_id & CAN_RTR_FLAG != 0 {
        Frame::WrongKind
    } else {
        Frame::Data {
            id: can_id & if extended { CAN_EFF_MASK } else { CAN_SFF_MASK },
            extended,
            fd: n == CANFD_MTU,
            len,
        }
    }
}

impl AsFd for RawSocket {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.socket.as_fd()
    }
}

/// CLOCK_MONOTONIC minus CLOCK_REALTIME now, ns: added to a kernel receive stamp, the
/// monotonic receive time.
pub fn realtime_offset() -> i128 {
    clock_ns(nix::time::ClockId::CLOCK_MONOTONIC) - realtime_now()
}

/// CLOCK_REALTIME now, ns: what a kernel receive stamp is on.
pub fn realtime_now() -> i128 {
    clock_ns(nix::time::ClockId::CLOCK_REALTIME)
}

/// Clock `id` now, ns (0 if unreadable, which never happens on Linux).
fn clock_ns(id: nix::time::ClockId) -> i128 {
    nix::time::clock_gettime(id)
        .map(|t| t.tv_sec() as i128 * 1_000_000_000 + t.tv_nsec() as i128)
        .unwrap_or(0)
}

/// `setsockopt(fd, level, name, value)` for the options no safe wrapper knows (the kernel
/// structs of CAN_ISOTP and CAN_J1939).
pub(crate) fn set_option<T: ?Sized>(
    fd: &impl AsRawFd,
    level: libc::c_int,
    name: libc::c_int,
    value: &T,
) -> std::io::Result<()> {
    #[allow(
        unsafe_code,
        reason = "CAN_ISOTP's and CAN_J1939's options are kernel structs no safe wrapper knows"
    )]
    // SAFETY: `value` is a live value of the size passed, read by the kernel during the
    // call only; `fd` is an open socket.
    let r = unsafe {
        libc::setsockopt(
            fd.as_raw_fd(),
            level,
            name,
            (value as *const T).cast(),
            std::mem::size_of_val(value) as libc::socklen_t,
        )
    };
    // SO_J1939_PROMISC and SO_J1939_ERRQUEUE return the value set, not 0.
    if r >= 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}
