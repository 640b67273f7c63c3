//! The socket side of a CAN card, serviced from one file descriptor.
//!
//! [`CanBus::open`] binds a CAN_RAW socket (FD-capable) to the card's interface with
//! kernel filters for exactly the mapped receive ids and every error class, and asks the
//! kernel for a receive timestamp and a drop count with each frame. [`CanBus::fds`] are
//! the descriptors that become readable when a frame arrives (the socket), when a frame is
//! due to be sent (a timerfd at the next deadline), or when an output changed on an
//! on-change frame (an eventfd); an rtt file-descriptor activity watches them and calls
//! [`CanBus::service`], which never blocks. That is how a J1939 card, with two sockets,
//! waits. A card without J1939 ([`CanBus::waits_in_socket`]) waits in the socket's own
//! `recvmsg` instead, as a bare blocking reader does ([`CanBus::wait_and_service`]): its
//! deadlines and wake-ups end that wait with a signal (see [`can_socket::blocking`]). The
//! socket is replaced when the interface is ([`CanBus::socket_generation`] says when).
//!
//! The link is watched through the socket's errors and `/sys/class/net/IF`: when it goes
//! down the card goes offline; when it comes back — even as a new interface of the same
//! name — the socket is reopened if needed and the card comes back by itself.
//!
//! ```no_run
//! # use std::sync::Arc;
//! # fn demo(card: Arc<driver_can::card::CanCard>) -> Result<(), driver_can::bus::BusError> {
//! let mut bus = driver_can::bus::CanBus::open(card)?;
//! loop {
//!     // (an fd activity waits for bus.fds() instead)
//!     std::thread::sleep(std::time::Duration::from_millis(1));
//!     bus.service(&mut |_frame, _payload, _received| {});
//! }
//! # }
//! ```

mod j1939;
mod link;

pub use can_socket::link::can_interfaces;

use crate::card::{CanCard, ErrorReport, Received};
use can_socket::socket::{
    Filter, Frame, RawSocket, check_interface, realtime_now, realtime_offset,
};
use can_socket::wakeups::Wakeups;
use device_interface::time::Timestamp;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd};
use std::sync::Arc;

/// Why a bus could not be opened (the socket layer's interface checks).
pub use can_socket::socket::InterfaceError as BusError;

/// A card's socket, timer and wake-up.
pub struct CanBus {
    card: Arc<CanCard>,
    socket: Option<RawSocket>,
    ifindex: u32,
    /// The interface's link state, read from sysfs files kept open.
    link: can_socket::link::LinkReader,
    /// Room for the frames one wait in the socket takes.
    batch: can_socket::batch::Batch,
    /// Counts the sockets opened (see [`CanBus::socket_generation`]).
    generation: u64,
    wakeups: Wakeups,
    /// Next send time (ns) of each cyclic tx frame.
    next_tx: Vec<Option<u64>>,
    next_check: u64,
    /// Room for the longest sent payload.
    buf: Vec<u8>,
    /// The J1939 socket and node (a card with a `[j1939]` table).
    j1939: Option<j1939::Side>,
    /// The PGNs the J1939 socket receives: the mapped ones, and a node's Request and
    /// Address Claimed.
    j1939_pgns: Vec<can_socket::j1939::Pgn>,
    /// The physical values of the frame just received (room for the widest rx frame).
    values: Vec<f64>,
    /// Waiting in the socket failed and was said (said again only after it worked).
    wait_failing: bool,
    /// Whether the interface is a real controller with a state to ask netlink for
    /// (unknown until asked; asked again when the interface is replaced).
    controller: Option<bool>,
}

fn now_ns() -> u64 {
    use device_interface::time::{Clock, MonotonicClock};
    MonotonicClock.now().as_nanos()
}

impl CanBus {
    /// Opens the card's interface. A missing or non-CAN interface, or FD frames on a
    /// classic interface, are errors; an interface that exists but is down is not (the
    /// card stays offline until it comes up).
    pub fn open(card: Arc<CanCard>) -> Result<CanBus, BusError> {
        let name = card.map().interface().to_string();
        let os = |what: &'static str| {
            let name = name.clone();
            move |source: std::io::Error| BusError::Os {
                name: name.clone(),
                what,
                source,
            }
        };
        let nix_os = |what: &'static str| {
            let f = os(what);
            move |e: nix::Error| f(std::io::Error::from(e))
        };
        let fd_frame = card.map().rx().iter().chain(card.map().tx()).find(|f| f.fd);
        let ifindex = check_interface(&name, fd_frame.map(|f| f.name.as_str()))?;
        let wakeups = Wakeups::new().map_err(|(what, e)| nix_os(what)(e))?;
        card.set_waker(wakeups.waker());
        let now = now_ns();
        let next_tx = card
            .map()
            .tx()
            .iter()
            .map(|f| f.cycle.map(|_| now))
            .collect();
        let widest = card.map().widest_rx();
        let longest_tx = card.map().longest(true);
        let j1939_pgns = j1939::pgns(card.map());
        let j1939 = card.map().j1939().map(|node| {
            j1939::Side::new(
                card.map().longest(false),
                node.map(|n| crate::j1939::Claimer::new(n).logging_to(card.log().clone())),
            )
        });
        let mut wakeups = wakeups;
        wakeups.wait_in_socket(j1939.is_none());
        let mut bus = CanBus {
            card,
            socket: None,
            ifindex,
            link: can_socket::link::LinkReader::new(&name),
            batch: can_socket::batch::Batch::default(),
            generation: 0,
            wakeups,
            next_tx,
            next_check: now,
            buf: vec![0; longest_tx],
            j1939_pgns,
            j1939,
            values: Vec::with_capacity(widest),
            wait_failing: false,
            controller: None,
        };
        bus.open_socket().map_err(os("open socket"))?;
        bus.check_link();
        bus.arm();
        Ok(bus)
    }

    fn open_socket(&mut self) -> std::io::Result<()> {
        // The thread's signal must not touch the descriptor once it is closed (its number
        // may be another file's by the next wait).
        self.wakeups.waiter().leave();
        self.socket = None;
        let map = self.card.map();
        // J1939 groups come through the J1939 socket.
        let filters: Vec<Filter> = map
            .rx()
            .iter()
            .filter(|f| f.j1939.is_none())
            .map(|f| Filter::exact(f.id, f.extended))
            .collect();
        let s = RawSocket::open(map.interface(), &filters)?;
        self.socket = Some(s);
        self.generation += 1;
        // A new interface: a new J1939 socket too (opened now if it can be, else when the
        // link is up).
        if let Some(side) = &mut self.j1939 {
            side.socket = None;
        }
        self.ensure_j1939();
        Ok(())
    }

    /// The descriptors to wait on, any of them readable when [`service`](Self::service)
    /// has work: the socket (none while the interface cannot be opened), the timer and the
    /// wake-up.
    pub fn fds(&self) -> impl Iterator<Item = BorrowedFd<'_>> {
        self.socket
            .as_ref()
            .map(|s| s.as_fd())
            .into_iter()
            .chain(self.j1939_fd())
            .chain(self.wakeups.fds())
    }

    /// The timer's and the wake-up's descriptors (never replaced).
    pub fn timer_fds(&self) -> impl Iterator<Item = BorrowedFd<'_>> {
        self.wakeups.fds().into_iter()
    }

    /// The J1939 socket's descriptor, if the card speaks J1939 and it is open.
    pub fn j1939_fd(&self) -> Option<BorrowedFd<'_>> {
        self.j1939.as_ref()?.socket.as_ref().map(|s| s.as_fd())
    }

    /// Changes whenever the J1939 socket is replaced (as
    /// [`socket_generation`](Self::socket_generation)).
    pub fn j1939_generation(&self) -> u64 {
        self.j1939.as_ref().map_or(0, |s| s.generation)
    }

    /// The socket's descriptor, if open.
    pub fn socket_fd(&self) -> Option<BorrowedFd<'_>> {
        self.socket.as_ref().map(|s| s.as_fd())
    }

    /// Changes whenever the socket is replaced (a new interface of the same name, or the
    /// first open after a failed one): whoever watches [`socket_fd`](Self::socket_fd) must
    /// then watch the new one (and let go of the old, which a duplicate would keep open).
    pub fn socket_generation(&self) -> u64 {
        self.generation
    }

    /// The card.
    pub fn card(&self) -> &Arc<CanCard> {
        &self.card
    }

    /// Does what is due without blocking: receives every queued frame (calling
    /// `on_frame(rx index, its signals' physical values, kernel receive time)` for each
    /// decoded one), sends changed and due frames, checks staleness and the link, and
    /// re-arms the timer.
    ///
    /// The socket comes first and costs one `recvmsg` per frame and one more (the EAGAIN
    /// that ends the batch); the wake-up and the timer are read only when they can have
    /// fired (a flag set with the wake-up; the deadline armed), and the timer is re-armed
    /// only when its deadline moves. A frame thus costs no other system call.
    pub fn service(&mut self, on_frame: &mut dyn FnMut(usize, &[f64], Timestamp)) {
        self.receive(on_frame);
        self.receive_j1939(on_frame);
        self.keep_time();
    }

    /// What [`service`](Self::service) does besides receiving: the wake-up, the link and
    /// staleness checks, the address claim, the frames due, the timer.
    fn keep_time(&mut self) {
        let now = now_ns();
        self.wakeups.clear(now);
        if now >= self.next_check {
            self.check_link();
            self.card.check_stale();
            self.next_check = now + self.card.map().link_check().as_nanos() as u64;
        }
        self.claim_step(now);
        self.send_due(now);
        self.arm();
    }

    fn receive(&mut self, on_frame: &mut dyn FnMut(usize, &[f64], Timestamp)) {
        // The kernel stamps frames with CLOCK_REALTIME; the card's time base is
        // CLOCK_MONOTONIC. One offset per batch (taken at its first frame) is exact to
        // well under a microsecond.
        let mut offset = None;
        let mut data = [0u8; 64];
        loop {
            let Some(socket) = &mut self.socket else {
                return;
            };
            let got = socket.recv(&mut data);
            if !self.take(got, &data, &mut offset, on_frame) {
                break;
            }
        }
    }

    /// Handles what one receive gave: a frame (decoded and handed to `on_frame`), an error
    /// frame, or the socket's error. False when nothing more is to be had now.
    fn take(
        &mut self,
        got: nix::Result<Option<can_socket::socket::Received>>,
        data: &[u8; 64],
        offset: &mut Option<i128>,
        on_frame: &mut dyn FnMut(usize, &[f64], Timestamp),
    ) -> bool {
        let got = match got {
            Ok(Some(got)) => got,
            Ok(None) => return false,
            Err(e @ (nix::Error::ENETDOWN | nix::Error::ENODEV)) => {
                self.link_lost(e);
                return false;
            }
            Err(e) => {
                rtt::rt_log!(
                    self.card.log(),
                    Warn,
                    "{}: recvmsg: {}",
                    rtt::log::Arg::text(self.card.map().interface()),
                    rtt::log::Arg::Errno(e as i32)
                );
                return false;
            }
        };
        if got.dropped > 0 {
            self.card.dropped(u64::from(got.dropped));
        }
        let at = match got.stamp {
            Some(real) => {
                let offset = *offset.get_or_insert_with(realtime_offset);
                Timestamp::from_nanos((real + offset).max(0) as u64)
            }
            None => Timestamp::from_nanos(now_ns()),
        };
        match got.frame {
            Frame::WrongKind => self.card.wrong_kind(),
            Frame::Error { class, len } => self.error_frame(class, &data[..len]),
            Frame::Data {
                id,
                extended,
                fd,
                len,
            } => {
                if let Received::Decoded(f) = self.card.receive_with_values(
                    id,
                    extended,
                    fd,
                    &data[..len],
                    at,
                    &mut self.values,
                ) {
                    on_frame(f, &self.values, at);
                }
            }
        }
        true
    }

    /// The thread that waited in the socket has ended (the component stopped): nothing
    /// aims at it any more (see [`can_socket::blocking::Waiter::forget_thread`]).
    pub fn thread_ended(&mut self) {
        self.wakeups.waiter().forget_thread();
    }

    /// True when the bus waits for its frames in the socket itself
    /// ([`wait_and_service`](Self::wait_and_service)): a card without J1939, whose socket
    /// is the only one to receive from.
    pub fn waits_in_socket(&self) -> bool {
        self.j1939.is_none()
    }

    /// Waits for something to do — in `recvmsg` on the socket for a frame, as a bare
    /// blocking reader does, ended early by a deadline or a wake-up (see
    /// [`can_socket::blocking`]); without a socket, in `poll` on the wake-up until the next
    /// deadline — then calls `woke` and does what [`service`](Self::service) does, the
    /// frames that ended the wait first. The wait is a `recvmmsg` that takes the frames
    /// queued behind the first (up to [`can_socket::batch::BATCH`]), and a full batch is
    /// followed by others that do not wait until one comes short, so a frame alone costs
    /// one call and a backlog one call a batch, with no call to learn that the queue is
    /// empty (reading one frame a step instead lost frames above 10 000 frames/s in the
    /// rig). For a bus that [`waits_in_socket`](Self::waits_in_socket), from one thread.
    pub fn wait_and_service(
        &mut self,
        woke: &mut dyn FnMut() -> Timestamp,
        on_frame: &mut dyn FnMut(usize, &[f64], Timestamp),
    ) {
        let mut data = [0u8; 64];
        let mut offset = None;
        match self.socket.as_ref().map(|s| s.as_fd().as_raw_fd()) {
            Some(fd) => match self.wakeups.waiter().prepare(fd) {
                Ok(true) => {
                    self.wait_failing = false;
                    let mut got = self
                        .socket
                        .as_mut()
                        .map(|s| s.recv_wait_batch(&mut self.batch));
                    // The wake-up's monotonic time, read once, gives the frames' stamps
                    // their offset with one more read (CLOCK_REALTIME), not two.
                    let at = woke().as_nanos();
                    // A full batch may have left frames queued: they are taken a batch
                    // at a time without waiting, until one comes short (the queue dry).
                    while let Some(Ok(n)) = got {
                        for k in 0..n {
                            let r = self.batch.frame(k, &mut data);
                            if offset.is_none() && r.stamp.is_some() {
                                offset = Some(i128::from(at) - realtime_now());
                            }
                            self.take(Ok(Some(r)), &data, &mut offset, on_frame);
                        }
                        if n < can_socket::batch::BATCH {
                            self.keep_time();
                            return;
                        }
                        got = self
                            .socket
                            .as_mut()
                            .map(|s| s.recv_batch_now(&mut self.batch));
                    }
                    if let Some(Err(e)) = got {
                        self.take(Err(e), &data, &mut offset, on_frame);
                    }
                }
                Ok(false) => {
                    woke();
                }
                Err(e) => {
                    if !self.wait_failing {
                        self.wait_failing = true;
                        rtt::rt_log!(
                            self.card.log(),
                            Warn,
                            "{}: cannot wait in the socket: {} (waiting in poll for the \
                             next deadline instead, until it can)",
                            rtt::log::Arg::text(self.card.map().interface()),
                            rtt::log::Arg::io(&e)
                        );
                    }
                    let deadline = self.next_deadline();
                    let socket = self.socket.as_ref().map(|s| s.as_fd());
                    self.wakeups.wait_in_poll(deadline, socket);
                    woke();
                }
            },
            None => {
                self.wakeups.waiter().leave();
                self.wakeups.wait_in_poll(self.next_deadline(), None);
                woke();
            }
        }
        self.service(on_frame);
    }

    fn error_frame(&self, class: u32, data: &[u8]) {
        let mut d = [0u8; 8];
        d[..data.len().min(8)].copy_from_slice(&data[..data.len().min(8)]);
        let Ok(frame) = socketcan::CanErrorFrame::new_error(class, &d) else {
            self.card.error_frame(ErrorReport::default());
            return;
        };
        let mut r = ErrorReport::default();
        for cause in frame.into_error().causes() {
            use socketcan::errors::{ControllerProblems as P, ErrorCause as C};
            match cause {
                C::TransmitTimeout => r.tx_timeout = true,
                C::LostArbitration(_) => r.lost_arbitration = true,
                C::Controller(p) => {
                    r.warning |= p.intersects(P::RX_WARNING | P::TX_WARNING);
                    r.passive |= p.intersects(P::RX_PASSIVE | P::TX_PASSIVE);
                    r.overflow |= p.intersects(P::RX_OVERFLOW | P::TX_OVERFLOW);
                    r.active |= p.contains(P::ACTIVE);
                }
                C::Protocol { .. } => r.protocol = true,
                C::Transceiver { .. } => r.transceiver = true,
                C::NoAck => r.no_ack = true,
                C::BusOff => r.bus_off = true,
                C::BusError => r.protocol = true,
                C::Restarted => r.restarted = true,
                _ => {}
            }
        }
        self.card.error_frame(r);
    }

    fn send_due(&mut self, now: u64) {
        let frames = self.card.map().tx().len();
        for t in 0..frames {
            let cycle = self.card.map().tx()[t].cycle;
            let due = self.next_tx[t].is_some_and(|d| now >= d);
            if !(due || self.card.is_dirty(t)) {
                continue;
            }
            if let (true, Some(c)) = (due, cycle) {
                // At least 1 ns (the map refuses cycles under 100 µs).
                let c = (c.as_nanos() as u64).max(1);
                let mut next = self.next_tx[t].unwrap_or(now) + c;
                // After a stall, keep the phase but do not send a burst of late frames;
                // the cycles left out are counted.
                if next <= now {
                    let skipped = (now - next) / c + 1;
                    next += skipped * c;
                    self.card.skipped(skipped);
                }
                self.next_tx[t] = Some(next);
            }
            self.send(t);
        }
    }

    fn send(&mut self, t: usize) {
        if self.card.map().tx()[t].j1939.is_some() {
            if self.card.link_up() {
                self.send_j1939(t);
            }
            return;
        }
        let len = self.card.compose(t, &mut self.buf);
        if !self.card.link_up() {
            return;
        }
        let Some(socket) = &self.socket else { return };
        let f = &self.card.map().tx()[t];
        let result = socket.send(f.id, f.extended, f.fd, &self.buf[..len]);
        if result
            .as_ref()
            .is_err_and(|e| e.kind() == std::io::ErrorKind::InvalidInput)
        {
            return;
        }
        if let Err(e) = &result {
            rtt::rt_log!(
                self.card.log(),
                Debug,
                "frame {} send failed: {}",
                rtt::log::Arg::text(&f.name),
                rtt::log::Arg::io(e)
            );
            if e.raw_os_error() == Some(nix::Error::ENETDOWN as i32) {
                self.link_lost(nix::Error::ENETDOWN);
            }
        }
        self.card.sent(result.is_ok());
    }

    /// Arms the timer for the next send or check.
    fn arm(&mut self) {
        let next = self.next_deadline();
        self.wakeups.arm(next);
    }

    /// The next send or check (monotonic ns).
    fn next_deadline(&self) -> u64 {
        self.next_tx
            .iter()
            .flatten()
            .copied()
            .chain([self.next_check])
            .chain(self.claim_deadline())
            .min()
            .unwrap_or(self.next_check)
    }
}
