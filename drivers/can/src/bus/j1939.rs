//! The J1939 side of a CAN card's bus: a `CAN_J1939` socket beside the CAN_RAW one,
//! receiving the parameter groups the card maps (the kernel filters by PGN; the card
//! matches source and priority) and the claims and requests of the address claiming, and
//! sending the card's J1939 groups from the address its node claimed, with the kernel's
//! transport carrying what is longer than a frame. The node's claims go out through a
//! second socket of their own: the kernel sends a socket's messages in turn, and a claim
//! must not wait behind a broadcast transfer (50 ms a packet) when a contest gives it
//! 250 ms. The node's address claiming ([`crate::j1939::Claimer`])
//! is fed the claims and requests received here; a new address binds the socket anew.

use super::{CanBus, now_ns};
use crate::card::Received;
use crate::j1939::{Claimer, Send};
use can_socket::j1939::{GLOBAL, J1939Socket, NULL_ADDRESS, Name, Pgn};
use can_socket::socket::realtime_offset;
use device_interface::time::Timestamp;
use rtt::log::Arg;
use rtt::rt_log;

/// A bus's J1939 socket and node.
pub(super) struct Side {
    pub(super) socket: Option<J1939Socket>,
    /// The socket the claims go out through (a node with a NAME), receiving nothing.
    claims: Option<J1939Socket>,
    /// The address the socket is bound to.
    bound: u8,
    pub(super) generation: u64,
    /// The node's claiming (a card with a NAME).
    claimer: Option<Claimer>,
    /// Whether the node claimed since the link last came up (or the socket was opened).
    claimed_on_link: bool,
    /// A socket said the interface went down: the kernel forgot the claims, and closed
    /// the sockets' transfers; they are opened anew (a carrier lost, at bus-off, is not
    /// this: the kernel keeps its claims then, and closing a socket with a transfer under
    /// way would wait for it).
    pub(super) reopen: bool,
    /// The next time a failed open is tried again, ns.
    open_at: u64,
    /// A claim or answer that could not be sent, sent again at `retry_at`.
    retry: Option<Send>,
    retry_at: u64,
    /// A group that could not be sent goes again at this time, ns.
    resend_at: Option<u64>,
    /// The kernel's drop counter as last seen.
    drops_seen: u32,
    /// An open failure was said (once until one succeeds).
    open_warned: bool,
    /// What the card was last told of the claiming.
    reported: Option<(crate::j1939::State, crate::j1939::ClaimCounts)>,
    /// Room for the longest mapped group and one byte more (a longer one is told by it).
    buf: Vec<u8>,
    /// A receive error was said (once per socket).
    warned: bool,
}

impl Side {
    pub(super) fn new(bus_longest_rx: usize, claimer: Option<Claimer>) -> Side {
        Side {
            socket: None,
            claims: None,
            bound: GLOBAL,
            generation: 0,
            claimer,
            claimed_on_link: false,
            reopen: false,
            open_at: 0,
            retry: None,
            retry_at: 0,
            resend_at: None,
            drops_seen: 0,
            open_warned: false,
            reported: None,
            warned: false,
            buf: vec![0; bus_longest_rx + 1],
        }
    }
}

/// The PGNs a card's J1939 socket receives: those its rx frames map, and for a node the
/// Request and Address Claimed its claiming answers.
pub(super) fn pgns(map: &crate::map::CanMap) -> Vec<Pgn> {
    let node = map.j1939().flatten().is_some();
    let mut pgns: Vec<Pgn> = map
        .rx()
        .iter()
        .filter_map(|f| f.j1939.map(|j| j.pgn))
        .chain(
            node.then_some([Pgn::REQUEST, Pgn::ADDRESS_CLAIMED])
                .into_iter()
                .flatten(),
        )
        .collect();
    pgns.sort();
    pgns.dedup();
    pgns
}

impl CanBus {
    /// (Re)opens the J1939 socket (on a new interface), bound to the node's NAME and
    /// address (none: receive only).
    pub(super) fn open_j1939(&mut self) -> std::io::Result<()> {
        let ifindex = self.ifindex;
        let Some(side) = &mut self.j1939 else {
            return Ok(());
        };
        side.socket = None;
        side.claims = None;
        let node = side
            .claimer
            .as_ref()
            .map(|c| (c.node().name, c.bound_address()));
        let socket = J1939Socket::open(ifindex, node, &self.j1939_pgns)?;
        if node.is_some() {
            side.claims = Some(J1939Socket::open(ifindex, node, &[])?);
        }
        side.socket = Some(socket);
        side.warned = false;
        side.open_warned = false;
        side.drops_seen = 0;
        // A new socket: the kernel holds no claim for it.
        side.claimed_on_link = false;
        side.retry = None;
        side.bound = node.map_or(GLOBAL, |(_, a)| a);
        side.generation += 1;
        Ok(())
    }

    /// Opens the J1939 socket if it is not open; a failure (the interface down: the
    /// kernel refuses the bind) is said once and tried again a link check later.
    pub(super) fn ensure_j1939(&mut self) {
        let now = now_ns();
        if self
            .j1939
            .as_ref()
            .is_none_or(|s| s.socket.is_some() || now < s.open_at)
        {
            return;
        }
        if let Err(e) = self.open_j1939() {
            let later = now + self.card.map().link_check().as_nanos() as u64;
            if let Some(side) = &mut self.j1939 {
                side.open_at = later;
                if !side.open_warned {
                    side.open_warned = true;
                    rt_log!(
                        self.card.log(),
                        Warn,
                        "{}: J1939 socket: {} (tried again while the link is up)",
                        Arg::text(self.card.map().interface()),
                        Arg::io(&e)
                    );
                }
            }
        }
    }

    /// A socket said the interface went down (ENETDOWN, ENODEV).
    pub(super) fn interface_down(&mut self) {
        if let Some(side) = &mut self.j1939 {
            side.reopen = true;
        }
    }

    /// Receives every queued parameter group: claims and requests go to the node, the
    /// rest to the card.
    pub(super) fn receive_j1939(&mut self, on_frame: &mut dyn FnMut(usize, &[f64], Timestamp)) {
        let mut offset = None;
        loop {
            let Some(side) = &mut self.j1939 else { return };
            let Some(socket) = &mut side.socket else {
                return;
            };
            let got = match socket.recv(&mut side.buf) {
                Ok(Some(got)) => got,
                Ok(None) => break,
                Err(e) => {
                    if gone(&e) {
                        self.link_lost(nix::Error::ENETDOWN);
                    } else if !side.warned {
                        side.warned = true;
                        rt_log!(
                            self.card.log(),
                            Warn,
                            "{}: J1939 recvmsg: {}",
                            Arg::text(self.card.map().interface()),
                            Arg::io(&e)
                        );
                    }
                    break;
                }
            };
            if let Some(d) = got.drops {
                let dropped = d.wrapping_sub(side.drops_seen);
                side.drops_seen = d;
                if dropped > 0 {
                    self.card.dropped(u64::from(dropped));
                }
            }
            // A group longer than any mapped one fills the buffer, whose length no mapped
            // group has: counted as a wrong length, not decoded.
            let len = got.len;
            let data = &side.buf[..len];
            let now = now_ns();
            let answer = match (&mut side.claimer, got.pgn) {
                (Some(c), Pgn::ADDRESS_CLAIMED) if len == 8 => {
                    let name = Name(u64::from_le_bytes(data.try_into().unwrap_or_default()));
                    Some(c.claim_seen(got.source, name, now))
                }
                // (A request may be padded to 8 bytes.)
                (Some(c), Pgn::REQUEST) if data.get(..3) == Some(&[0x00, 0xEE, 0x00]) => {
                    Some(c.request_seen(got.destination, now))
                }
                _ => None,
            };
            if let Some(send) = answer {
                if let Some(send) = send
                    && !self.claim_send(send)
                {
                    self.retry_claim(send, now);
                }
                self.report_claim();
                continue;
            }
            let at = match got.stamp {
                Some(real) => {
                    let offset = *offset.get_or_insert_with(realtime_offset);
                    Timestamp::from_nanos((real + offset).max(0) as u64)
                }
                None => Timestamp::from_nanos(now),
            };
            let Some(side) = &self.j1939 else { return };
            let data = &side.buf[..len];
            if let Received::Decoded(f) = self.card.receive_j1939(
                got.pgn,
                got.source,
                got.priority,
                data,
                at,
                &mut self.values,
            ) {
                on_frame(f, &self.values, at);
            }
        }
    }

    /// Follows the interface: one that went down (the kernel forgot the claims) takes the
    /// sockets with it, and one that is up gets sockets and a claim of the configured
    /// address; then sends again what could not be sent, moves the claim on with time, and
    /// reports it.
    pub(super) fn claim_step(&mut self, now: u64) {
        let up = self.card.link_up();
        let Some(side) = &mut self.j1939 else { return };
        if std::mem::take(&mut side.reopen) {
            side.socket = None;
            side.claims = None;
        }
        if side.resend_at.is_some_and(|at| now >= at) {
            side.resend_at = None;
        }
        if !up {
            return;
        }
        self.ensure_j1939();
        let Some(side) = &mut self.j1939 else { return };
        if side.socket.is_none() {
            return;
        }
        let Some(c) = &mut side.claimer else { return };
        let send = if !side.claimed_on_link {
            side.claimed_on_link = true;
            c.start(now)
        } else if side.retry.is_some() && now >= side.retry_at {
            side.retry.take()
        } else {
            c.tick(now)
        };
        if let Some(send) = send
            && !self.claim_send(send)
        {
            self.retry_claim(send, now);
        }
        self.report_claim();
    }

    /// Keeps `send`, which could not be sent, to be sent again shortly.
    fn retry_claim(&mut self, send: Send, now: u64) {
        if let Some(side) = &mut self.j1939 {
            side.retry = Some(send);
            side.retry_at = now + RETRY_NS;
        }
    }

    /// When the J1939 side next needs a step, ns: none while the link is down or the
    /// socket not open (the link check steps it then).
    pub(super) fn claim_deadline(&self) -> Option<u64> {
        let side = self.j1939.as_ref()?;
        if !self.card.link_up() || side.socket.is_none() {
            return None;
        }
        let claim = side
            .claimer
            .as_ref()
            .filter(|_| side.claimed_on_link)
            .and_then(Claimer::deadline);
        let retry = side.retry.map(|_| side.retry_at);
        [claim, retry, side.resend_at].into_iter().flatten().min()
    }

    /// Tells the card where the claiming stands, when that changed.
    fn report_claim(&mut self) {
        let Some(side) = &mut self.j1939 else { return };
        let Some(c) = &side.claimer else { return };
        let now = Some((c.state(), c.counts()));
        if side.reported != now {
            side.reported = now;
            self.card.set_claim(c.node().name, c.state(), c.counts());
        }
    }

    /// Sends a claim or Cannot Claim Address, from the address it must come from (the
    /// socket is bound anew when that changed). False when it could not be sent.
    fn claim_send(&mut self, send: Send) -> bool {
        let Some(side) = &self.j1939 else {
            return false;
        };
        let Some(c) = &side.claimer else {
            return false;
        };
        let name = c.node().name;
        let from = match send {
            Send::Claim(a) => a,
            Send::CannotClaim => NULL_ADDRESS,
        };
        let (Some(socket), Some(claims)) = (&side.socket, &side.claims) else {
            return false;
        };
        if side.bound != from {
            // Both: the groups go out from the new address, and a transfer to it is
            // answered.
            let rebound = claims
                .rebind(self.ifindex, Some((name, from)))
                .and_then(|()| socket.rebind(self.ifindex, Some((name, from))));
            if let Err(e) = rebound {
                rt_log!(
                    self.card.log(),
                    Warn,
                    "{}: J1939 socket for address {}: {}",
                    Arg::text(self.card.map().interface()),
                    Arg::display(&format_args!("{from:#x}")),
                    Arg::io(&e)
                );
                return false;
            }
            if let Some(side) = &mut self.j1939 {
                side.bound = from;
            }
        }
        let Some(claims) = self.j1939.as_ref().and_then(|s| s.claims.as_ref()) else {
            return false;
        };
        let sent = claims.send(Pgn::ADDRESS_CLAIMED, GLOBAL, 6, &name.0.to_le_bytes());
        if let Err(e) = &sent {
            rt_log!(
                self.card.log(),
                Warn,
                "{}: J1939 address claim from {}: {}",
                Arg::text(self.card.map().interface()),
                Arg::display(&format_args!("{from:#x}")),
                Arg::io(e)
            );
        }
        self.card.sent(sent.is_ok());
        sent.is_ok()
    }

    /// Sends tx frame `t`, a J1939 group, when the node holds an address; else it stays
    /// marked, and an on-change frame is sent once the claim holds.
    pub(super) fn send_j1939(&mut self, t: usize) {
        let f = &self.card.map().tx()[t];
        let Some(j) = f.j1939 else { return };
        let Some(side) = &self.j1939 else { return };
        if side
            .claimer
            .as_ref()
            .and_then(Claimer::sending_address)
            .is_none()
        {
            return;
        }
        let Some(socket) = &side.socket else { return };
        let len = self.card.compose(t, &mut self.buf);
        let sent = socket.send(
            j.pgn,
            j.destination,
            j.priority.unwrap_or(6),
            &self.buf[..len],
        );
        self.card.sent(sent.is_ok());
        let Err(e) = sent else { return };
        rt_log!(
            self.card.log(),
            Debug,
            "J1939 frame {}: send failed: {}",
            Arg::text(&f.name),
            Arg::io(&e)
        );
        if gone(&e) {
            self.link_lost(nix::Error::ENETDOWN);
        }
        // A transient refusal (a full queue, a transfer under way, an address the kernel
        // has not mapped yet or no longer: a contest the receive side is about to see):
        // its values go out at the next try, shortly, not lost with this one.
        let transient = [
            nix::Error::EAGAIN,
            nix::Error::ENOBUFS,
            nix::Error::EBUSY,
            nix::Error::EADDRNOTAVAIL,
            nix::Error::ENETDOWN,
        ];
        if transient
            .iter()
            .any(|t| e.raw_os_error() == Some(*t as i32))
        {
            self.card.resend(t);
            if let Some(side) = &mut self.j1939 {
                side.resend_at = Some(now_ns() + RETRY_NS);
            }
        }
    }
}

/// How soon a claim or group that could not be sent is tried again, ns.
const RETRY_NS: u64 = 20_000_000;

/// An error that says the interface went down or away.
fn gone(e: &std::io::Error) -> bool {
    [nix::Error::ENETDOWN, nix::Error::ENODEV]
        .iter()
        .any(|g| e.raw_os_error() == Some(*g as i32))
}
