//! The socket side of a CANopen card, serviced from one file descriptor set: a CAN_RAW
//! socket (the shared `can-socket` layer) filtered to exactly the COB-IDs of the managed
//! nodes — TPDOs, emergencies, SDO responses, heartbeats — a timerfd at the next SYNC,
//! timeout or link check, and an eventfd an output change writes. [`CanopenBus::service`]
//! never blocks: it routes each received frame to its node or PDO, runs the nodes' state
//! machines, sends SYNC and the RPDOs due (on change, or after each SYNC for synchronous
//! ones) and whatever the nodes queued (NMT, SDO requests), and re-arms the timer.
//!
//! The link is checked every 100 ms through sysfs: down, the card is offline (the nodes
//! then lose their heartbeats); back, the socket is reopened if the interface was
//! replaced and each node that boots up or is heard again is configured again.

use crate::card::CanopenCard;
use crate::node::{NodeRun, Tx};
use can_socket::link::LinkReader;
use can_socket::socket::{
    Filter, Frame, InterfaceError, RawSocket, check_interface, realtime_offset,
};
use can_socket::wakeups::Wakeups;
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use std::os::fd::{AsFd, BorrowedFd};
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// How often the link is checked.
const LINK_CHECK: u64 = 100_000_000;

/// The most frames kept for a full transmit queue.
const QUEUED: usize = 1024;

/// What a received COB-ID is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Route {
    None,
    Tpdo(usize),
    Emcy(usize),
    Sdo(usize),
    Heartbeat(usize),
}

fn now_ns() -> u64 {
    MonotonicClock.now().as_nanos()
}

/// A CANopen card's socket, timer, wake-up and node managers.
pub struct CanopenBus {
    card: Arc<CanopenCard>,
    socket: Option<RawSocket>,
    ifindex: u32,
    /// The interface's link state, read from sysfs files kept open.
    link: LinkReader,
    generation: u64,
    wakeups: Wakeups,
    nodes: Vec<NodeRun>,
    routes: Vec<Route>,
    out: Vec<Tx>,
    next_sync: Option<u64>,
    next_check: u64,
    started: bool,
}

impl CanopenBus {
    /// Opens the card's interface: an error when it is missing or not CAN (the node
    /// managers come back with it); down is fine (the card is offline until it comes up).
    pub fn open(
        card: Arc<CanopenCard>,
        nodes: Vec<NodeRun>,
    ) -> Result<CanopenBus, (InterfaceError, Vec<NodeRun>)> {
        let name = card.map().interface.clone();
        let wakeups = match check_interface(&name, None).and_then(|ifindex| {
            let w = Wakeups::new().map_err(|(what, e)| InterfaceError::Os {
                name: name.clone(),
                what,
                source: e.into(),
            })?;
            Ok((ifindex, w))
        }) {
            Ok(ok) => ok,
            Err(e) => return Err((e, nodes)),
        };
        let (ifindex, wakeups) = wakeups;
        card.set_waker(wakeups.waker());
        let mut routes = vec![Route::None; 0x800];
        for (p, pdo) in card.map().tpdos.iter().enumerate() {
            routes[usize::from(pdo.cob_id)] = Route::Tpdo(p);
        }
        for (n, node) in card.map().nodes.iter().enumerate() {
            let id = usize::from(node.id);
            routes[0x80 + id] = Route::Emcy(n);
            routes[0x580 + id] = Route::Sdo(n);
            routes[0x700 + id] = Route::Heartbeat(n);
        }
        let now = now_ns();
        let mut bus = CanopenBus {
            next_sync: card.map().sync.map(|_| now),
            card,
            socket: None,
            ifindex,
            link: LinkReader::new(&name),
            generation: 0,
            wakeups,
            nodes,
            routes,
            out: Vec::with_capacity(64),
            next_check: now,
            started: false,
        };
        match bus.open_socket() {
            Ok(()) => Ok(bus),
            Err(source) => Err((
                InterfaceError::Os {
                    name,
                    what: "open socket",
                    source,
                },
                bus.nodes,
            )),
        }
    }

    fn open_socket(&mut self) -> std::io::Result<()> {
        self.socket = None;
        let filters: Vec<Filter> = self
            .routes
            .iter()
            .enumerate()
            .filter(|(_, r)| **r != Route::None)
            .map(|(id, _)| Filter::exact(id as u32, false))
            .collect();
        self.socket = Some(RawSocket::open(&self.card.map().interface, &filters)?);
        self.generation += 1;
        Ok(())
    }

    /// The descriptors to wait on: the socket (none while it cannot be opened), the timer
    /// and the wake-up.
    pub fn fds(&self) -> impl Iterator<Item = BorrowedFd<'_>> {
        self.socket
            .as_ref()
            .map(|s| s.as_fd())
            .into_iter()
            .chain(self.wakeups.fds())
    }

    /// The socket's descriptor, if open.
    pub fn socket_fd(&self) -> Option<BorrowedFd<'_>> {
        self.socket.as_ref().map(|s| s.as_fd())
    }

    /// Changes whenever the socket is replaced.
    pub fn socket_generation(&self) -> u64 {
        self.generation
    }

    /// The card.
    pub fn card(&self) -> &Arc<CanopenCard> {
        &self.card
    }

    /// Does what is due, without blocking.
    pub fn service(&mut self) {
        let now = self.receive();
        self.wakeups.clear(now);
        if now >= self.next_check {
            self.check_link();
            self.next_check = now + LINK_CHECK;
        }
        if self.card.link_up() {
            if !self.started {
                self.started = true;
                for node in &mut self.nodes {
                    node.start(now, &mut self.out);
                }
            }
            for node in &mut self.nodes {
                node.tick(now, &mut self.out);
            }
        }
        // What the frames and timeouts changed, once per step (before the drives and
        // RPDOs, which need a started node's outputs seeded).
        self.publish();
        if self.card.link_up() {
            crate::drive::step(&self.card);
            self.send_sync(now);
            self.send_rpdos(false);
        }
        self.flush();
        self.arm();
    }

    fn receive(&mut self) -> u64 {
        let mut data = [0u8; 64];
        let mut offset = None;
        while let Some(socket) = &mut self.socket {
            let got = match socket.recv(&mut data) {
                Ok(Some(got)) => got,
                Ok(None) => break,
                Err(e) => {
                    if matches!(e, nix::Error::ENETDOWN | nix::Error::ENODEV) {
                        self.card.set_link(false);
                    } else {
                        tracing::warn!(interface = %self.card.map().interface, "recvmsg: {e}");
                    }
                    break;
                }
            };
            let c = &self.card.counters;
            c.rx_frames.fetch_add(1, Ordering::Relaxed);
            if got.dropped > 0 {
                c.dropped
                    .fetch_add(u64::from(got.dropped), Ordering::Relaxed);
            }
            let at = match got.stamp {
                Some(real) => {
                    let offset = *offset.get_or_insert_with(realtime_offset);
                    (real + offset).max(0) as u64
                }
                None => now_ns(),
            };
            match got.frame {
                Frame::Error { .. } => {
                    c.error_frames.fetch_add(1, Ordering::Relaxed);
                }
                Frame::Data {
                    id,
                    extended: false,
                    fd: false,
                    len,
                } => self.route(id, &data[..len], at),
                _ => {
                    c.wrong_kind.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        now_ns()
    }

    fn route(&mut self, id: u32, data: &[u8], at: u64) {
        let route = self.routes.get(id as usize).copied().unwrap_or(Route::None);
        match route {
            Route::None => {
                self.card
                    .counters
                    .wrong_kind
                    .fetch_add(1, Ordering::Relaxed);
            }
            Route::Tpdo(p) => {
                if self.card.node_operational(self.card.map().tpdos[p].node) {
                    self.card.receive(p, data, Timestamp::from_nanos(at));
                }
            }
            Route::Emcy(n) => self.nodes[n].on_emcy(data),
            Route::Sdo(n) => self.nodes[n].on_sdo(data, at, &mut self.out),
            Route::Heartbeat(n) => self.nodes[n].on_heartbeat(data, at, &mut self.out),
        }
    }

    /// Hands changed node states to the card.
    fn publish(&mut self) {
        for (n, node) in self.nodes.iter_mut().enumerate() {
            if node.changed {
                node.changed = false;
                for (index, sub, data) in node.outputs_read.drain(..) {
                    self.card.seed(n, index, sub, &data);
                }
                self.card.set_node(n, node.status(), node.is_operational());
            }
        }
    }

    fn send_sync(&mut self, now: u64) {
        let (Some(next), Some(period)) = (self.next_sync, self.card.map().sync) else {
            return;
        };
        if now < next {
            return;
        }
        let period = (period.as_nanos() as u64).max(1);
        let mut following = next + period;
        if following <= now {
            following += (now - following) / period * period + period;
        }
        self.next_sync = Some(following);
        self.out.push(Tx {
            id: 0x80,
            len: 0,
            data: [0; 8],
        });
        self.card.counters.syncs.fetch_add(1, Ordering::Relaxed);
        self.send_rpdos(true);
    }

    /// Queues the RPDOs of operational nodes: the synchronous ones (after a SYNC), or the
    /// event-driven ones that changed.
    fn send_rpdos(&mut self, sync: bool) {
        let card = self.card.clone();
        for (p, pdo) in card.map().rpdos.iter().enumerate() {
            if !card.node_operational(pdo.node) {
                continue;
            }
            let due = if sync {
                pdo.sync
            } else {
                !pdo.sync && card.is_dirty(p)
            };
            if due {
                let mut data = [0u8; 8];
                let len = card.compose(p, &mut data);
                self.out.push(Tx {
                    id: pdo.cob_id,
                    len: len as u8,
                    data,
                });
                card.counters.rpdos.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Sends what is queued, in order. A full transmit queue (the controller's, or the
    /// socket's buffer) keeps the frame and those after it for the next step (at most
    /// [`QUEUED`]; older ones are dropped and counted); any other failure drops the frame
    /// and counts it.
    fn flush(&mut self) {
        let Some(socket) = &self.socket else {
            self.out.clear();
            return;
        };
        let mut sent = 0;
        for tx in &self.out {
            let len = usize::from(tx.len).min(8);
            match socket.send(u32::from(tx.id), false, false, &tx.data[..len]) {
                Ok(()) => {}
                Err(e)
                    if e.kind() == std::io::ErrorKind::WouldBlock
                        || e.raw_os_error() == Some(nix::Error::ENOBUFS as i32) =>
                {
                    break;
                }
                Err(e) => {
                    tracing::debug!(id = tx.id, "send failed: {e}");
                    self.card
                        .counters
                        .send_errors
                        .fetch_add(1, Ordering::Relaxed);
                }
            }
            sent += 1;
        }
        self.out.drain(..sent);
        if self.out.len() > QUEUED {
            let over = self.out.len() - QUEUED;
            self.out.drain(..over);
            self.card
                .counters
                .send_errors
                .fetch_add(over as u64, Ordering::Relaxed);
        }
    }

    fn check_link(&mut self) {
        match self.link.read() {
            None => self.card.set_link(false),
            Some((up, index)) => {
                if index != self.ifindex || self.socket.is_none() {
                    self.ifindex = index;
                    if let Err(e) = self.open_socket() {
                        tracing::warn!(interface = %self.card.map().interface, "cannot reopen: {e}");
                        self.card.set_link(false);
                        return;
                    }
                }
                if up != self.card.link_up() {
                    tracing::info!(interface = %self.card.map().interface, up, "link");
                }
                self.card.set_link(up);
            }
        }
    }

    /// Leaves the nodes as the section's `at_stop` says (the outputs were settled first).
    pub fn stop(&mut self) {
        let at_stop = self.card.map().at_stop;
        for node in &self.nodes {
            node.stop(at_stop, &mut self.out);
        }
        // The stop's frames get a bounded while (100 ms) for a full transmit queue.
        for _ in 0..50 {
            self.flush();
            if self.out.is_empty() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        if !self.out.is_empty() {
            tracing::warn!(
                interface = %self.card.map().interface,
                "{} frames of the stop not sent: the transmit queue stayed full",
                self.out.len()
            );
        }
    }

    fn arm(&mut self) {
        let next = self
            .nodes
            .iter()
            .filter_map(|n| n.next_deadline())
            .chain(self.next_sync)
            .chain([self.next_check])
            // Frames kept for a full transmit queue: tried again in 1 ms.
            .chain((!self.out.is_empty()).then(|| now_ns() + 1_000_000))
            .min()
            .unwrap_or(self.next_check);
        self.wakeups.arm(next);
    }
}
