//! J1939-81 address claiming for a card's node, as a state machine without I/O: the bus
//! side feeds it the claims and requests it receives and the time, and sends what it says.
//!
//! - At start, and each time the link comes back, the node claims its address (PGN
//!   0xEE00 from that address, its NAME as data) and uses it once no contender came for
//!   250 ms (ISO 11783-5 §4.5.2 d; the kernel's J1939 stack maps a NAME to its address
//!   after the same time, so hwgw waits [`CLAIM_WAIT_NS`], a little longer).
//! - A claim of the node's address by another NAME is a contest the lower NAME wins. The
//!   winner sends its claim again. The loser stops sending on that address and, if its NAME
//!   is arbitrary-address capable (bit 63), claims the next address of 128–247 no other
//!   NAME holds; otherwise it sends Cannot Claim Address (a claim from the null address
//!   254) and stays without an address.
//! - A Request for Address Claimed (PGN 0xEA00 asking for 0xEE00), to everyone or to the
//!   node, is answered with its claim; a node without an address answers with Cannot Claim
//!   after a pseudo-random delay of 0 to 153 ms, so that several such nodes do not collide.
//!
//! ```
//! use can_socket::j1939::Name;
//! use driver_can::j1939::{Claimer, Send, State};
//! use driver_can::map::J1939Node;
//!
//! let mut c = Claimer::new(J1939Node { name: Name(0x20), address: 0x80 });
//! assert_eq!(c.start(0), Some(Send::Claim(0x80)));
//! // Another node claims 0x80 with a lower NAME: ours is not arbitrary-address capable.
//! assert_eq!(c.claim_seen(0x80, Name(0x10), 1), Some(Send::CannotClaim));
//! assert_eq!(c.state(), State::CannotClaim);
//! ```

use crate::map::J1939Node;
use can_socket::j1939::{GLOBAL, NULL_ADDRESS, Name};
use rtt::log::{Area, Arg};
use rtt::rt_log;

/// How long a node waits after its claim before it uses the address, ns: the standard's
/// 250 ms and 10 ms more, as the kernel starts its own 250 ms when it sees the claim go
/// out (a group sent before the kernel has mapped the address would be refused).
pub const CLAIM_WAIT_NS: u64 = 260_000_000;

/// Where a node stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "state", content = "address")]
pub enum State {
    /// It claimed this address and waits for contenders.
    Claiming(u8),
    /// It holds this address.
    Claimed(u8),
    /// It lost its address and cannot claim another.
    CannotClaim,
}

/// What the node must send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Send {
    /// Its claim, from this address.
    Claim(u8),
    /// Cannot Claim Address, from the null address.
    CannotClaim,
}

/// What the claiming did so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ClaimCounts {
    /// Contests for the node's address it won (its claim sent again).
    pub won: u64,
    /// Contests it lost (to a lower NAME).
    pub lost: u64,
    /// Requests for Address Claimed answered.
    pub requests: u64,
}

/// A node's address claiming.
#[derive(Debug, Clone)]
pub struct Claimer {
    node: J1939Node,
    state: State,
    /// While claiming: when the address may be used (CLOCK_MONOTONIC ns).
    usable_at: u64,
    /// A Cannot Claim answer due at this time.
    cannot_claim_due: Option<u64>,
    /// The NAME each address was last claimed by (other nodes only).
    held: [Option<Name>; 254],
    counts: ClaimCounts,
    /// Where its claims, contests and losses are told (through the real-time logger: it
    /// runs on the bus's thread); none: not told.
    log: Option<Area>,
}

impl Claimer {
    /// A node that has not claimed yet (it claims at [`start`](Self::start)).
    pub fn new(node: J1939Node) -> Claimer {
        Claimer {
            node,
            state: State::Claiming(node.address),
            usable_at: u64::MAX,
            cannot_claim_due: None,
            held: [None; 254],
            counts: ClaimCounts::default(),
            log: None,
        }
    }

    /// The same, telling its claims, contests and losses through `log`.
    pub fn logging_to(mut self, log: Area) -> Claimer {
        self.log = Some(log);
        self
    }

    /// Its node.
    pub fn node(&self) -> J1939Node {
        self.node
    }

    /// Claims the configured address (again: after the link came back), at `now` ns.
    pub fn start(&mut self, now: u64) -> Option<Send> {
        self.cannot_claim_due = None;
        Some(self.claim(self.node.address, now))
    }

    fn claim(&mut self, address: u8, now: u64) -> Send {
        self.state = State::Claiming(address);
        self.usable_at = now + CLAIM_WAIT_NS;
        Send::Claim(address)
    }

    /// Where it stands.
    pub fn state(&self) -> State {
        self.state
    }

    /// What the claiming did.
    pub fn counts(&self) -> ClaimCounts {
        self.counts
    }

    /// The address it may send parameter groups from now, if any.
    pub fn sending_address(&self) -> Option<u8> {
        match self.state {
            State::Claimed(a) => Some(a),
            _ => None,
        }
    }

    /// The address its socket must be bound to: the one claimed, or the null address.
    pub fn bound_address(&self) -> u8 {
        match self.state {
            State::Claiming(a) | State::Claimed(a) => a,
            State::CannotClaim => NULL_ADDRESS,
        }
    }

    /// The next time [`tick`](Self::tick) has something to do, ns.
    pub fn deadline(&self) -> Option<u64> {
        let claiming = matches!(self.state, State::Claiming(_)).then_some(self.usable_at);
        [claiming, self.cannot_claim_due]
            .into_iter()
            .flatten()
            .min()
    }

    /// Time passed: a claim not contested for long enough holds; a delayed answer is due.
    pub fn tick(&mut self, now: u64) -> Option<Send> {
        if let State::Claiming(a) = self.state
            && now >= self.usable_at
        {
            self.state = State::Claimed(a);
            if let Some(log) = &self.log {
                rt_log!(
                    log,
                    Info,
                    "J1939 node {}: address {} claimed",
                    Arg::display(&self.node.name),
                    a
                );
            }
        }
        match self.cannot_claim_due {
            Some(due) if now >= due => {
                self.cannot_claim_due = None;
                Some(Send::CannotClaim)
            }
            _ => None,
        }
    }

    /// A claim came from `source` with `name`, at `now` ns.
    pub fn claim_seen(&mut self, source: u8, name: Name, now: u64) -> Option<Send> {
        if name == self.node.name {
            // Its own claim, as the bus carried it.
            return None;
        }
        // A NAME holds one address: the one it claimed last.
        for h in self.held.iter_mut().filter(|h| **h == Some(name)) {
            *h = None;
        }
        if source == NULL_ADDRESS || source == GLOBAL {
            return None;
        }
        self.held[usize::from(source)] = Some(name);
        let ours = match self.state {
            State::Claiming(a) | State::Claimed(a) if a == source => a,
            _ => return None,
        };
        if self.node.name < name {
            self.counts.won += 1;
            if let Some(log) = &self.log {
                rt_log!(
                    log,
                    Info,
                    "J1939 node {}: contest for address {} with {} won: claiming again",
                    Arg::display(&self.node.name),
                    ours,
                    Arg::display(&name)
                );
            }
            return Some(Send::Claim(ours));
        }
        self.counts.lost += 1;
        let next = self
            .node
            .name
            .arbitrary_address_capable()
            .then(|| (128..=247u8).find(|&a| a != ours && self.held[usize::from(a)].is_none()));
        match next.flatten() {
            Some(a) => {
                if let Some(log) = &self.log {
                    rt_log!(
                        log,
                        Warn,
                        "J1939 node {}: address {} lost to {}: claiming {}",
                        Arg::display(&self.node.name),
                        ours,
                        Arg::display(&name),
                        a
                    );
                }
                Some(self.claim(a, now))
            }
            None => {
                if let Some(log) = &self.log {
                    rt_log!(
                        log,
                        Warn,
                        "J1939 node {}: address {} lost to {}: cannot claim another",
                        Arg::display(&self.node.name),
                        ours,
                        Arg::display(&name)
                    );
                }
                self.state = State::CannotClaim;
                Some(Send::CannotClaim)
            }
        }
    }

    /// A Request for Address Claimed came, sent to `destination`, at `now` ns.
    pub fn request_seen(&mut self, destination: u8, now: u64) -> Option<Send> {
        match self.state {
            State::Claiming(a) | State::Claimed(a) if destination == GLOBAL || destination == a => {
                self.counts.requests += 1;
                Some(Send::Claim(a))
            }
            State::CannotClaim if destination == GLOBAL => {
                self.counts.requests += 1;
                // 0 to 153 ms in steps of 0.6 ms (J1939-81), from bits that differ
                // between nodes and between requests.
                let spread = (self.node.name.0 ^ now ^ (now >> 17)) % 256;
                self.cannot_claim_due = Some(now + spread * 600_000);
                None
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn node(name: u64, address: u8) -> Claimer {
        Claimer::new(J1939Node {
            name: Name(name),
            address,
        })
    }

    #[test]
    fn a_claim_holds_when_no_contender_came_in_time() {
        let mut c = node(0x100, 0x20);
        assert_eq!(c.start(10 * MS), Some(Send::Claim(0x20)));
        assert_eq!(c.sending_address(), None);
        assert_eq!(c.deadline(), Some(270 * MS));
        assert_eq!(c.tick(269 * MS), None);
        assert_eq!(c.state(), State::Claiming(0x20));
        c.tick(270 * MS);
        assert_eq!(c.sending_address(), Some(0x20));
        assert_eq!(c.deadline(), None);
    }

    #[test]
    fn the_lower_name_wins_and_the_winner_claims_again() {
        let mut c = node(0x100, 0x80);
        c.start(0);
        c.tick(300 * MS);
        // A higher NAME contests: ours wins, is sent again, and the address stays.
        assert_eq!(
            c.claim_seen(0x80, Name(0x200), 301 * MS),
            Some(Send::Claim(0x80))
        );
        assert_eq!(c.state(), State::Claimed(0x80));
        // Its own claim as the bus carried it changes nothing.
        assert_eq!(c.claim_seen(0x80, Name(0x100), 302 * MS), None);
        // Claims for other addresses are only noted.
        assert_eq!(c.claim_seen(0x81, Name(0x50), 303 * MS), None);
        // A lower NAME takes the address: not arbitrary-address capable, it cannot claim.
        assert_eq!(
            c.claim_seen(0x80, Name(0x50), 304 * MS),
            Some(Send::CannotClaim)
        );
        assert_eq!((c.state(), c.sending_address()), (State::CannotClaim, None));
        assert_eq!(c.bound_address(), NULL_ADDRESS);
        assert_eq!((c.counts().won, c.counts().lost), (1, 1));
    }

    #[test]
    fn an_arbitrary_address_capable_node_moves_to_a_free_address() {
        let capable = 0x8000_0000_0000_0100;
        let mut c = node(capable, 0x80);
        c.start(0);
        // 0x80 and 0x81 are others'.
        c.claim_seen(0x81, Name(0x9000_0000_0000_0000), MS);
        assert_eq!(
            c.claim_seen(0x80, Name(0x10), 2 * MS),
            Some(Send::Claim(0x82))
        );
        assert_eq!(c.state(), State::Claiming(0x82));
        assert_eq!(c.deadline(), Some(262 * MS));
        // The NAME at 0x81 moves away: its old address is free again.
        c.claim_seen(0x90, Name(0x9000_0000_0000_0000), 3 * MS);
        assert_eq!(
            c.claim_seen(0x82, Name(0x11), 4 * MS),
            Some(Send::Claim(0x81))
        );
    }

    #[test]
    fn a_node_with_no_address_left_cannot_claim() {
        let mut c = node(0x8000_0000_0000_0100, 0x80);
        c.start(0);
        for (k, a) in (128..=247u8).enumerate() {
            c.claim_seen(a, Name(k as u64 + 1), MS);
            if c.state() == State::CannotClaim {
                break;
            }
        }
        assert_eq!(c.state(), State::CannotClaim);
    }

    #[test]
    fn requests_are_answered() {
        let mut c = node(0x100, 0x80);
        c.start(0);
        assert_eq!(c.request_seen(GLOBAL, MS), Some(Send::Claim(0x80)));
        assert_eq!(c.request_seen(0x80, MS), Some(Send::Claim(0x80)));
        assert_eq!(c.request_seen(0x81, MS), None, "a request for another node");
        c.claim_seen(0x80, Name(1), 2 * MS);
        // Without an address: Cannot Claim, 0 to 153 ms later.
        assert_eq!(c.request_seen(GLOBAL, 10 * MS), None);
        let due = c.deadline().unwrap();
        assert!((10 * MS..=163 * MS).contains(&due), "{due}");
        assert_eq!(c.tick(due), Some(Send::CannotClaim));
        assert_eq!(c.tick(due + MS), None);
        assert_eq!(c.counts().requests, 3);
    }
}
