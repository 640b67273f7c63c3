//! Frames received in one call: `recvmmsg` with `MSG_WAITFORONE`, which waits (on a
//! blocking socket, see [`crate::blocking`]) for the first frame and takes what is queued
//! behind it, up to [`BATCH`], without waiting again. A reader that waits in its socket
//! thus makes one call a frame when frames come one at a time — no second call to learn
//! that nothing else is queued — and one call for up to [`BATCH`] when they queue up.
//!
//! The headers are built on the stack at each call, with each frame's control-message
//! room at its full size: the kernel writes back how much of it a frame used, and a room
//! left at that size would cut off the drop count of a later frame (nix's `recvmmsg`
//! keeps the written-back size, so it is not used here).

use crate::socket::{CANFD_MTU, RawSocket, Received, frame_of};
use std::os::fd::{AsFd, AsRawFd};

/// The most frames one call takes.
pub const BATCH: usize = 16;

/// Control-message room per frame: a timestamp (`timespec`) and a drop count (`u32`),
/// each with its header, with room to spare; 8-byte aligned.
const CMSG_WORDS: usize = 16;

/// Room for [`BATCH`] frames and what the kernel says of each, allocated once.
pub struct Batch {
    raw: Box<[[u8; CANFD_MTU]; BATCH]>,
    cmsg: Box<[[u64; CMSG_WORDS]; BATCH]>,
    /// Per frame received: its length, its kernel stamp (CLOCK_REALTIME ns), the frames
    /// dropped before it.
    got: [(usize, Option<i128>, u32); BATCH],
    len: usize,
}

impl Default for Batch {
    fn default() -> Self {
        Batch {
            raw: Box::new([[0; CANFD_MTU]; BATCH]),
            cmsg: Box::new([[0; CMSG_WORDS]; BATCH]),
            got: [(0, None, 0); BATCH],
            len: 0,
        }
    }
}

impl Batch {
    /// How many frames the last call took.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the last call took none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Frame `k` of the last call, its payload copied into `data`.
    pub fn frame(&self, k: usize, data: &mut [u8; 64]) -> Received {
        debug_assert!(k < self.len, "frame {k} of a batch of {}", self.len);
        let (n, stamp, dropped) = self.got[k];
        Received {
            frame: frame_of(&self.raw[k], n, data),
            stamp,
            dropped,
        }
    }
}

impl RawSocket {
    /// Receives up to [`BATCH`] frames in one call, waiting for the first when the socket
    /// is blocking (see [`crate::blocking`]): how many, 0 when the wait was interrupted
    /// (EINTR) or the socket was non-blocking with nothing queued. The error is the
    /// socket's (ENETDOWN or ENODEV when the link went).
    pub fn recv_wait_batch(&mut self, batch: &mut Batch) -> nix::Result<usize> {
        self.recv_batch(batch, libc::MSG_WAITFORONE)
    }

    /// As [`recv_wait_batch`](Self::recv_wait_batch), never waiting: what is queued, up
    /// to [`BATCH`] frames, for the rest of a backlog after a full batch.
    pub fn recv_batch_now(&mut self, batch: &mut Batch) -> nix::Result<usize> {
        self.recv_batch(batch, libc::MSG_DONTWAIT)
    }

    fn recv_batch(&mut self, batch: &mut Batch, flags: libc::c_int) -> nix::Result<usize> {
        batch.len = 0;
        let mut iov: [libc::iovec; BATCH] = std::array::from_fn(|k| libc::iovec {
            iov_base: batch.raw[k].as_mut_ptr().cast(),
            iov_len: CANFD_MTU,
        });
        let mut headers: [libc::mmsghdr; BATCH] = std::array::from_fn(|k| {
            // SAFETY: an all-zero msghdr is a valid one (no name, no iovecs, no control).
            #[allow(unsafe_code, reason = "a zeroed libc struct, filled in below")]
            let mut h: libc::mmsghdr = unsafe { std::mem::zeroed() };
            h.msg_hdr.msg_iov = &mut iov[k];
            h.msg_hdr.msg_iovlen = 1;
            h.msg_hdr.msg_control = batch.cmsg[k].as_mut_ptr().cast();
            h.msg_hdr.msg_controllen = std::mem::size_of::<[u64; CMSG_WORDS]>() as _;
            h
        });
        let fd = self.as_fd().as_raw_fd();
        #[allow(unsafe_code, reason = "recvmmsg into buffers this function owns")]
        // SAFETY: every header points at an iovec of `CANFD_MTU` bytes of `batch.raw` and
        // at `batch.cmsg`'s room of the size given, all alive and unaliased for the call.
        let n = unsafe {
            libc::recvmmsg(
                fd,
                headers.as_mut_ptr(),
                BATCH as u32,
                flags,
                std::ptr::null_mut(),
            )
        };
        if n < 0 {
            return match nix::Error::last() {
                nix::Error::EINTR | nix::Error::EAGAIN => Ok(0),
                e => Err(e),
            };
        }
        let n = n as usize;
        for (k, h) in headers.iter().enumerate().take(n) {
            let (stamp, drops) = control(&h.msg_hdr);
            let dropped = self.dropped_since(drops);
            batch.got[k] = (h.msg_len as usize, stamp, dropped);
        }
        batch.len = n;
        Ok(n)
    }
}

/// The kernel stamp (CLOCK_REALTIME ns) and the drop counter among a received message's
/// control messages.
fn control(h: &libc::msghdr) -> (Option<i128>, Option<u32>) {
    let (mut stamp, mut drops) = (None, None);
    #[allow(
        unsafe_code,
        reason = "walking the control messages the kernel wrote into this header's room"
    )]
    // SAFETY: `h` was filled by recvmmsg: its control pointer and length describe the
    // room given, of which the kernel wrote `msg_controllen` bytes of well-formed control
    // messages; each datum is read unaligned, at its header's data pointer.
    unsafe {
        let mut c = libc::CMSG_FIRSTHDR(h);
        while !c.is_null() {
            let data = libc::CMSG_DATA(c);
            match ((*c).cmsg_level, (*c).cmsg_type) {
                (libc::SOL_SOCKET, libc::SCM_TIMESTAMPNS) => {
                    let t = std::ptr::read_unaligned(data.cast::<libc::timespec>());
                    stamp = Some(i128::from(t.tv_sec) * 1_000_000_000 + i128::from(t.tv_nsec));
                }
                (libc::SOL_SOCKET, libc::SO_RXQ_OVFL) => {
                    drops = Some(std::ptr::read_unaligned(data.cast::<u32>()));
                }
                _ => {}
            }
            c = libc::CMSG_NXTHDR(h, c);
        }
    }
    (stamp, drops)
}
