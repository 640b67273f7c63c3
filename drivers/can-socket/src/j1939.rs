//! SAE J1939 through the kernel's `CAN_J1939` sockets (`can-j1939.ko`): parameter groups
//! received with their PGN, source and destination address and priority, messages of any
//! length the kernel's transport carries (TP up to 1785 bytes, ETP beyond) received whole
//! and sent in one call; and the arithmetic of 29-bit ids, PGNs and NAMEs.
//!
//! The socket is bound to a node's NAME and the address it claims (or to neither, for a
//! listener), promiscuous (it sees every parameter group on the bus, whoever it is for),
//! non-blocking, with receive timestamps. Address claiming (J1939-81) is the caller's: it
//! sends the claims (PGN 0xEE00, which the kernel takes only from a socket bound to the
//! NAME the claim carries) and [`rebind`](J1939Socket::rebind)s to a new address. The
//! kernel keeps a table of the addresses claimed on the bus and sends a NAME-bound
//! socket's groups from its NAME's address, 250 ms after the claim and while no lower
//! NAME has taken it (EADDRNOTAVAIL otherwise).
//!
//! ```
//! use can_socket::j1939::{Pgn, parts};
//!
//! // EEC1 from the engine (SA 0x00), priority 3.
//! let p = parts(0x0CF0_0400);
//! assert_eq!((p.pgn, p.source, p.priority, p.destination), (Pgn(0xF004), 0x00, 3, 0xFF));
//! // A PDU1 group: the PS byte is the destination, not part of the PGN.
//! let p = parts(0x18EA_2017);
//! assert_eq!((p.pgn, p.source, p.destination), (Pgn(0xEA00), 0x17, 0x20));
//! ```

use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd};

/// A parameter group number (18 bits; a PDU1 group's low byte is 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Pgn(pub u32);

impl Pgn {
    /// Request (J1939-21).
    pub const REQUEST: Pgn = Pgn(0xEA00);
    /// Address Claimed / Cannot Claim Address (J1939-81).
    pub const ADDRESS_CLAIMED: Pgn = Pgn(0xEE00);

    /// A PDU1 group (PF below 240): sent to one destination address.
    pub fn is_pdu1(self) -> bool {
        (self.0 >> 8) & 0xFF < 240
    }
}

impl std::fmt::Display for Pgn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#06x}", self.0)
    }
}

/// The global (broadcast) address; also "no address".
pub const GLOBAL: u8 = 0xFF;
/// The null address a node without one sends Cannot Claim Address from.
pub const NULL_ADDRESS: u8 = 0xFE;
/// The largest message the kernel's transport carries: ETP's (2^24 − 1) × 7 bytes.
pub const MAX_MESSAGE: usize = ((1 << 24) - 1) * 7;

/// What a 29-bit id says in J1939 terms.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IdParts {
    /// The PGN (a PDU1 group's destination byte cleared).
    pub pgn: Pgn,
    /// Priority, 0 (highest) to 7.
    pub priority: u8,
    /// Source address.
    pub source: u8,
    /// Destination address (PDU1), else [`GLOBAL`].
    pub destination: u8,
}

/// Splits a 29-bit id.
pub fn parts(id: u32) -> IdParts {
    let raw = Pgn((id >> 8) & 0x3FFFF);
    let (pgn, destination) = if raw.is_pdu1() {
        (Pgn(raw.0 & 0x3FF00), (raw.0 & 0xFF) as u8)
    } else {
        (raw, GLOBAL)
    };
    IdParts {
        pgn,
        priority: ((id >> 26) & 7) as u8,
        source: (id & 0xFF) as u8,
        destination,
    }
}

/// A J1939 NAME (64 bits, J1939-81): the lower value wins an address conflict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Name(pub u64);

impl Name {
    /// Bit 63: the node may take another address when it loses its own.
    pub fn arbitrary_address_capable(self) -> bool {
        self.0 >> 63 == 1
    }
}

impl std::fmt::Display for Name {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#018x}", self.0)
    }
}

/// One received parameter group, its payload in the caller's buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Message {
    /// The bytes of it in the buffer.
    pub len: usize,
    /// It was longer than the buffer (the rest is lost).
    pub truncated: bool,
    /// Its PGN.
    pub pgn: Pgn,
    /// The sender's address.
    pub source: u8,
    /// The address it was sent to ([`GLOBAL`] for a broadcast).
    pub destination: u8,
    /// Its priority.
    pub priority: u8,
    /// The kernel's receive time, CLOCK_REALTIME ns.
    pub stamp: Option<i128>,
    /// The socket's count of messages dropped for a full queue, when the kernel said it.
    pub drops: Option<u32>,
}

/// A non-blocking, promiscuous `CAN_J1939` socket bound to one interface and address.
pub struct J1939Socket {
    fd: OwnedFd,
    /// The priority the socket sends with now (set only when it changes).
    priority: std::cell::Cell<u8>,
}

fn last_error() -> std::io::Error {
    std::io::Error::last_os_error()
}

fn set<T: ?Sized>(
    fd: &OwnedFd,
    level: libc::c_int,
    name: libc::c_int,
    value: &T,
) -> std::io::Result<()> {
    crate::socket::set_option(fd, level, name, value)
}

/// A `sockaddr_can` for J1939 on interface `ifindex`.
fn address(ifindex: u32, name: u64, pgn: u32, addr: u8) -> libc::sockaddr_can {
    #[allow(unsafe_code, reason = "sockaddr_can holds a union")]
    // SAFETY: all-zero bytes are a valid sockaddr_can (integers and a union of integers).
    let mut a: libc::sockaddr_can = unsafe { std::mem::zeroed() };
    a.can_family = libc::AF_CAN as libc::sa_family_t;
    a.can_ifindex = ifindex as libc::c_int;
    a.can_addr.j1939.name = name;
    a.can_addr.j1939.pgn = pgn;
    a.can_addr.j1939.addr = addr;
    a
}

impl J1939Socket {
    /// Opens a socket on interface `ifindex` bound to `name` and `address` (none: a
    /// listener, which cannot send; address [`NULL_ADDRESS`]: to send Cannot Claim
    /// Address), receiving parameter groups `receive` whoever they are for (none: a
    /// socket that only sends; more than 512: all), broadcasts allowed.
    pub fn open(
        ifindex: u32,
        node: Option<(Name, u8)>,
        receive: &[Pgn],
    ) -> std::io::Result<J1939Socket> {
        #[allow(unsafe_code, reason = "nix has no CAN_J1939 socket")]
        // SAFETY: plain socket(2); the descriptor it returns (checked) is owned from here.
        let fd = unsafe {
            let fd = libc::socket(
                libc::PF_CAN,
                libc::SOCK_DGRAM | libc::SOCK_NONBLOCK | libc::SOCK_CLOEXEC,
                libc::CAN_J1939,
            );
            if fd < 0 {
                return Err(last_error());
            }
            OwnedFd::from_raw_fd(fd)
        };
        let on: libc::c_int = 1;
        set(&fd, libc::SOL_CAN_J1939, libc::SO_J1939_PROMISC, &on)?;
        set(&fd, libc::SOL_SOCKET, libc::SO_BROADCAST, &on)?;
        set(&fd, libc::SOL_SOCKET, libc::SO_TIMESTAMPNS, &on)?;
        set(&fd, libc::SOL_SOCKET, libc::SO_RXQ_OVFL, &on)?;
        let socket = J1939Socket {
            fd,
            priority: std::cell::Cell::new(6),
        };
        // The filter before the bind: nothing else is queued meanwhile.
        socket.receive_only(receive)?;
        socket.rebind(ifindex, node)?;
        Ok(socket)
    }

    /// Receives only parameter groups `pgns` (the kernel's filter; at most 512, else
    /// every group), none when empty: a socket that only sends.
    fn receive_only(&self, pgns: &[Pgn]) -> std::io::Result<()> {
        let exact = |pgn: u32, addr: u8, addr_mask: u8| libc::j1939_filter {
            name: 0,
            name_mask: 0,
            pgn,
            pgn_mask: libc::J1939_PGN_MAX,
            addr,
            addr_mask,
        };
        let filters: Vec<libc::j1939_filter> = if pgns.is_empty() {
            // A PDU1 PGN with a destination byte, which the kernel clears in every PGN it
            // receives: nothing matches.
            vec![exact(0xEF01, 0, 0)]
        } else if pgns.len() <= 512 {
            pgns.iter().map(|p| exact(p.0, 0, 0)).collect()
        } else {
            return Ok(());
        };
        set(
            &self.fd,
            libc::SOL_CAN_J1939,
            libc::SO_J1939_FILTER,
            filters.as_slice(),
        )
    }

    /// Binds the socket (again) to `name` and `address` on interface `ifindex` (the one
    /// it was opened on); the kernel's table of claimed addresses is kept.
    pub fn rebind(&self, ifindex: u32, node: Option<(Name, u8)>) -> std::io::Result<()> {
        let (name, addr) = node.map_or((libc::J1939_NO_NAME, GLOBAL), |(n, a)| (n.0, a));
        let a = address(ifindex, name, libc::J1939_NO_PGN, addr);
        #[allow(unsafe_code, reason = "nix has no sockaddr_can")]
        // SAFETY: `a` is a valid sockaddr_can of the size given, read during the call.
        let r = unsafe {
            libc::bind(
                self.fd.as_raw_fd(),
                (&a as *const libc::sockaddr_can).cast(),
                std::mem::size_of::<libc::sockaddr_can>() as libc::socklen_t,
            )
        };
        if r != 0 {
            return Err(last_error());
        }
        Ok(())
    }

    /// Receives one queued message into `buf` without blocking: none when none is queued
    /// (EINTR is retried). A message longer than `buf` is cut and said to be.
    pub fn recv(&mut self, buf: &mut [u8]) -> std::io::Result<Option<Message>> {
        // Room for a timespec, the drop count and the three J1939 control messages (128
        // bytes), aligned, and to spare.
        let mut cmsg = [0u64; 32];
        #[allow(unsafe_code, reason = "sockaddr_can holds a union")]
        // SAFETY: all-zero bytes are a valid sockaddr_can.
        let mut from: libc::sockaddr_can = unsafe { std::mem::zeroed() };
        let mut iov = libc::iovec {
            iov_base: buf.as_mut_ptr().cast(),
            iov_len: buf.len(),
        };
        #[allow(unsafe_code, reason = "msghdr holds raw pointers")]
        // SAFETY: all-zero bytes are a valid msghdr (null pointers, zero lengths).
        let mut msg: libc::msghdr = unsafe { std::mem::zeroed() };
        msg.msg_name = (&mut from as *mut libc::sockaddr_can).cast();
        msg.msg_namelen = std::mem::size_of::<libc::sockaddr_can>() as libc::socklen_t;
        msg.msg_iov = &mut iov;
        msg.msg_iovlen = 1;
        msg.msg_control = cmsg.as_mut_ptr().cast();
        msg.msg_controllen = std::mem::size_of_val(&cmsg);
        let n = loop {
            #[allow(unsafe_code, reason = "nix cannot return a sockaddr_can")]
            // SAFETY: every pointer in `msg` points at a live buffer of the length given
            // (`from`, `buf` through `iov`, `cmsg`), all outliving the call.
            let n = unsafe { libc::recvmsg(self.fd.as_raw_fd(), &mut msg, libc::MSG_DONTWAIT) };
            if n >= 0 {
                break n as usize;
            }
            let e = last_error();
            match e.raw_os_error() {
                Some(libc::EAGAIN) => return Ok(None),
                Some(libc::EINTR) => continue,
                _ => return Err(e),
            }
        };
        #[allow(
            unsafe_code,
            reason = "the j1939 member is the union's one for CAN_J1939"
        )]
        // SAFETY: the kernel filled `from` as a J1939 address.
        let (pgn, source) = unsafe { (from.can_addr.j1939.pgn, from.can_addr.j1939.addr) };
        let mut got = Message {
            len: n.min(buf.len()),
            truncated: msg.msg_flags & libc::MSG_TRUNC != 0,
            pgn: Pgn(pgn),
            source,
            destination: GLOBAL,
            priority: 6,
            stamp: None,
            drops: None,
        };
        #[allow(
            unsafe_code,
            reason = "control messages are read through libc's CMSG macros"
        )]
        // SAFETY: `msg` is the header recvmsg filled, its control buffer `cmsg` live; the
        // CMSG macros stay within `msg_controllen`, and each payload is read unaligned with
        // the size its type has.
        unsafe {
            let mut c = libc::CMSG_FIRSTHDR(&msg);
            while !c.is_null() {
                let data = libc::CMSG_DATA(c);
                match ((*c).cmsg_level, (*c).cmsg_type) {
                    (libc::SOL_SOCKET, libc::SCM_TIMESTAMPNS) => {
                        let t = std::ptr::read_unaligned(data.cast::<libc::timespec>());
                        got.stamp = Some(t.tv_sec as i128 * 1_000_000_000 + t.tv_nsec as i128);
                    }
                    (libc::SOL_SOCKET, libc::SO_RXQ_OVFL) => {
                        got.drops = Some(std::ptr::read_unaligned(data.cast::<u32>()));
                    }
                    (libc::SOL_CAN_J1939, libc::SCM_J1939_DEST_ADDR) => got.destination = *data,
                    (libc::SOL_CAN_J1939, libc::SCM_J1939_PRIO) => got.priority = *data,
                    _ => {}
                }
                c = libc::CMSG_NXTHDR(&msg, c);
            }
        }
        Ok(Some(got))
    }

    /// Sends `data` (any length the transport carries) as parameter group `pgn` to
    /// `destination` ([`GLOBAL`]: broadcast) with `priority`. Without blocking: a message
    /// the kernel cannot take now is an error (EAGAIN, ENOBUFS), as is one to a
    /// destination a transfer is already going to.
    pub fn send(
        &self,
        pgn: Pgn,
        destination: u8,
        priority: u8,
        data: &[u8],
    ) -> std::io::Result<()> {
        if self.priority.get() != priority {
            let p = libc::c_int::from(priority);
            set(&self.fd, libc::SOL_CAN_J1939, libc::SO_J1939_SEND_PRIO, &p)?;
            self.priority.set(priority);
        }
        let to = address(0, libc::J1939_NO_NAME, pgn.0, destination);
        #[allow(unsafe_code, reason = "nix has no sockaddr_can")]
        // SAFETY: `data` and `to` are live for the call, with the lengths given.
        let n = unsafe {
            libc::sendto(
                self.fd.as_raw_fd(),
                data.as_ptr().cast(),
                data.len(),
                libc::MSG_DONTWAIT,
                (&to as *const libc::sockaddr_can).cast(),
                std::mem::size_of::<libc::sockaddr_can>() as libc::socklen_t,
            )
        };
        match usize::try_from(n) {
            Err(_) => Err(last_error()),
            Ok(n) if n == data.len() => Ok(()),
            // Only an ETP message is queued in parts; hwgw sends TP sizes (1785 at most).
            Ok(n) => Err(std::io::Error::other(format!(
                "{n} of {} bytes queued",
                data.len()
            ))),
        }
    }
}

impl AsFd for J1939Socket {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_split_as_j1939_21_says() {
        // PDU2 (PF ≥ 240): the PS byte is a group extension, part of the PGN.
        let p = parts(0x18FE_F100 | 0x21);
        assert_eq!(p.pgn, Pgn(0xFEF1));
        assert_eq!((p.priority, p.source, p.destination), (6, 0x21, GLOBAL));
        // The data page bit is part of the PGN.
        assert_eq!(parts(0x19FE_F100).pgn, Pgn(0x1FEF1));
        // PDU1: the destination is not.
        let p = parts(0x18EE_FF80);
        assert_eq!(
            (p.pgn, p.destination, p.source),
            (Pgn::ADDRESS_CLAIMED, 0xFF, 0x80)
        );
        assert!(Pgn(0xEF00).is_pdu1() && !Pgn(0xF000).is_pdu1());
    }

    #[test]
    fn names_order_and_capability() {
        assert!(Name(0x8000_0000_0000_0000).arbitrary_address_capable());
        assert!(!Name(0x7FFF_FFFF_FFFF_FFFF).arbitrary_address_capable());
        assert!(Name(1) < Name(2));
        assert_eq!(Name(0xA).to_string(), "0x000000000000000a");
    }
}
