//! ISO-TP (ISO 15765-2) through the kernel's `CAN_ISOTP` sockets: a request of any length
//! up to 4095 bytes sent and the response received, segmentation and flow control done by
//! the kernel (`can-isotp.ko`) with the block size, separation time and padding a
//! deployment gives. What UDS diagnostics run on.
//!
//! The socket is opened for each exchange and closed after it, so an interface that was
//! replaced is simply used again; one exchange at a time per address pair (a second socket
//! bound to the same ids would answer the peer's flow control twice).

use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::Duration;

/// `SOL_CAN_ISOTP`.
const SOL_CAN_ISOTP: libc::c_int = libc::SOL_CAN_BASE + libc::CAN_ISOTP;
/// `CAN_ISOTP_OPTS`: a `struct can_isotp_options`.
const CAN_ISOTP_OPTS: libc::c_int = 1;
/// `CAN_ISOTP_RECV_FC`: a `struct can_isotp_fc_options`.
const CAN_ISOTP_RECV_FC: libc::c_int = 2;
/// Pad sent frames to 8 bytes.
const CAN_ISOTP_TX_PADDING: u32 = 0x004;
/// The largest request (a classic ISO-TP message).
pub const MAX_LEN: usize = 4095;
/// The largest response taken: the kernel's default `max_pdu_size`.
pub const MAX_RESPONSE: usize = 8300;

/// `struct can_isotp_options` (linux/can/isotp.h).
#[repr(C)]
#[derive(Default)]
struct Options {
    flags: u32,
    frame_txtime: u32,
    ext_address: u8,
    txpad_content: u8,
    rxpad_content: u8,
    rx_ext_address: u8,
}

/// `struct can_isotp_fc_options`.
#[repr(C)]
struct FlowControl {
    bs: u8,
    stmin: u8,
    wftmax: u8,
}

/// One ISO-TP address pair and how it talks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IsoTp {
    /// The id hwgw sends on (the ECU's request id, e.g. 0x7E0).
    pub tx_id: u32,
    /// The id the answer comes on (e.g. 0x7E8).
    pub rx_id: u32,
    /// 29-bit ids.
    pub extended: bool,
    /// Block size hwgw asks of the sender (0: all frames without waiting).
    pub block_size: u8,
    /// Separation time hwgw asks of the sender, in ISO 15765-2's STmin coding (0-127 ms,
    /// 0xF1-0xF9: 100-900 µs).
    pub st_min: u8,
    /// Pad sent frames to 8 bytes with this byte.
    pub padding: Option<u8>,
    /// How long to wait for the response.
    pub timeout: Duration,
}

/// Why an exchange failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum IsoTpError {
    /// The request is empty or longer than ISO-TP carries.
    #[error("a request is 1 to {MAX_LEN} bytes, not {0}")]
    Length(usize),
    /// The socket could not be opened, set up or bound.
    #[error("interface {interface:?}: {what}: {source}")]
    Open {
        /// The interface.
        interface: String,
        /// What was being done.
        what: &'static str,
        /// The error.
        source: std::io::Error,
    },
    /// Sending failed.
    #[error("sending {len} bytes to {tx_id:#x}: {source}")]
    Send {
        /// The request's length.
        len: usize,
        /// The id sent on.
        tx_id: u32,
        /// The error.
        source: std::io::Error,
    },
    /// No response in time, or receiving failed.
    #[error("no response on {rx_id:#x} within {timeout:?}")]
    Timeout {
        /// The id listened on.
        rx_id: u32,
        /// The time waited.
        timeout: Duration,
    },
    /// A response longer than [`MAX_RESPONSE`]: refused, not cut.
    #[error("the response on {rx_id:#x} is {len} bytes, more than the {MAX_RESPONSE} taken")]
    TooLong {
        /// The id listened on.
        rx_id: u32,
        /// Its length.
        len: usize,
    },
    /// Receiving failed (ECOMM: the peer's flow control did not come, or a frame of the
    /// response was missing).
    #[error("receiving on {rx_id:#x}: {source}")]
    Receive {
        /// The id listened on.
        rx_id: u32,
        /// The error.
        source: std::io::Error,
    },
}

fn setsockopt<T>(fd: &OwnedFd, name: libc::c_int, value: &T) -> std::io::Result<()> {
    crate::socket::set_option(fd, SOL_CAN_ISOTP, name, value)
}

impl IsoTp {
    fn flag(&self, id: u32) -> u32 {
        if self.extended {
            id | crate::socket::CAN_EFF_FLAG
        } else {
            id
        }
    }

    /// A socket on `interface` bound to this address pair.
    fn open(&self, interface: &str) -> Result<OwnedFd, IsoTpError> {
        let fail = |what: &'static str, source: std::io::Error| IsoTpError::Open {
            interface: interface.into(),
            what,
            source,
        };
        let ifindex = nix::net::if_::if_nametoindex(interface)
            .map_err(|e| fail("no such interface", e.into()))?;
        #[allow(unsafe_code, reason = "nix has no CAN_ISOTP socket")]
        // SAFETY: plain socket(2); the descriptor it returns (checked) is owned from here.
        let fd = unsafe {
            let fd = libc::socket(
                libc::PF_CAN,
                libc::SOCK_DGRAM | libc::SOCK_CLOEXEC,
                libc::CAN_ISOTP,
            );
            if fd < 0 {
                return Err(fail("socket", std::io::Error::last_os_error()));
            }
            OwnedFd::from_raw_fd(fd)
        };
        let mut options = Options::default();
        if let Some(pad) = self.padding {
            options.flags |= CAN_ISOTP_TX_PADDING;
            options.txpad_content = pad;
        }
        setsockopt(&fd, CAN_ISOTP_OPTS, &options).map_err(|e| fail("options", e))?;
        let fc = FlowControl {
            bs: self.block_size,
            stmin: self.st_min,
            wftmax: 0,
        };
        setsockopt(&fd, CAN_ISOTP_RECV_FC, &fc).map_err(|e| fail("flow control", e))?;
        #[allow(unsafe_code, reason = "nix has no sockaddr_can")]
        // SAFETY: a zeroed sockaddr_can is valid; its tp member is the union's one used
        // for CAN_ISOTP; bind reads the struct of the size given during the call.
        let r = unsafe {
            let mut addr: libc::sockaddr_can = std::mem::zeroed();
            addr.can_family = libc::AF_CAN as libc::sa_family_t;
            addr.can_ifindex = ifindex as libc::c_int;
            addr.can_addr.tp.rx_id = self.flag(self.rx_id);
            addr.can_addr.tp.tx_id = self.flag(self.tx_id);
            libc::bind(
                fd.as_raw_fd(),
                (&addr as *const libc::sockaddr_can).cast(),
                std::mem::size_of::<libc::sockaddr_can>() as libc::socklen_t,
            )
        };
        if r != 0 {
            return Err(fail("bind", std::io::Error::last_os_error()));
        }
        nix::sys::socket::setsockopt(
            &fd,
            nix::sys::socket::sockopt::ReceiveTimeout,
            &nix::sys::time::TimeVal::new(
                self.timeout.as_secs() as libc::time_t,
                self.timeout.subsec_micros() as libc::suseconds_t,
            ),
        )
        .map_err(|e| fail("receive timeout", e.into()))?;
        Ok(fd)
    }

    /// Sends `request` on `interface` and returns the response.
    pub fn exchange(&self, interface: &str, request: &[u8]) -> Result<Vec<u8>, IsoTpError> {
        if request.is_empty() || request.len() > MAX_LEN {
            return Err(IsoTpError::Length(request.len()));
        }
        let fd = self.open(interface)?;
        nix::unistd::write(&fd, request).map_err(|e| IsoTpError::Send {
            len: request.len(),
            tx_id: self.tx_id,
            source: e.into(),
        })?;
        // Room for the largest message the kernel reassembles by default (its
        // max_pdu_size, 8300); MSG_TRUNC tells a longer one, refused rather than cut.
        let mut buf = vec![0u8; MAX_RESPONSE];
        loop {
            match nix::sys::socket::recv(
                fd.as_raw_fd(),
                &mut buf,
                nix::sys::socket::MsgFlags::MSG_TRUNC,
            ) {
                Ok(n) if n > buf.len() => {
                    return Err(IsoTpError::TooLong {
                        rx_id: self.rx_id,
                        len: n,
                    });
                }
                Ok(n) => {
                    buf.truncate(n);
                    return Ok(buf);
                }
                Err(nix::Error::EINTR) => continue,
                Err(nix::Error::EAGAIN) => {
                    return Err(IsoTpError::Timeout {
                        rx_id: self.rx_id,
                        timeout: self.timeout,
                    });
                }
                Err(e) => {
                    return Err(IsoTpError::Receive {
                        rx_id: self.rx_id,
                        source: e.into(),
                    });
                }
            }
        }
    }
}
