//! J1939 in a card's map. With a `[j1939]` table, a card's extended (29-bit) frames are
//! J1939 parameter groups: a received one is matched by its PGN, whatever its priority and
//! source address unless the frame pins them (`source`, `priority`); a sent one goes from
//! the card's claimed address with the id's priority and (PDU1) destination unless the
//! frame says otherwise. Its length is the DBC message's, up to what the kernel's
//! transport carries. Standard frames stay plain CAN frames.

use super::{MapError, MappedFrame, bad};
use crate::section::{CanConfig, FrameConfig, J1939Config};
use can_socket::j1939::{GLOBAL, Name, Pgn, parts};

/// What a J1939 frame is matched by, or sent as.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct J1939Frame {
    /// Its parameter group.
    pub pgn: Pgn,
    /// rx: only from this source address (none: any).
    pub source: Option<u8>,
    /// rx: only of this priority (none: any); tx: the priority sent with.
    pub priority: Option<u8>,
    /// tx: where it goes ([`GLOBAL`] for a PDU2 group or a broadcast).
    pub destination: u8,
}

/// Who the card is on the network: the NAME it claims `address` with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct J1939Node {
    /// Its NAME.
    pub name: Name,
    /// The address it claims first.
    pub address: u8,
}

/// The largest address a node can claim (254 is the null address, 255 global).
const LAST_ADDRESS: u8 = 253;

/// The longest group hwgw sends: what TP carries (ETP, beyond, is received only).
pub const MAX_SENT: usize = 1785;

/// The PGNs the kernel's transport and hwgw's address claiming use themselves: TP.DT,
/// TP.CM, ETP.DT, ETP.CM, Request, Address Claimed.
const RESERVED: [(u32, &str); 6] = [
    (0xEB00, "the transport protocol's data transfer (TP.DT)"),
    (
        0xEC00,
        "the transport protocol's connection management (TP.CM)",
    ),
    (
        0xC700,
        "the extended transport protocol's data transfer (ETP.DT)",
    ),
    (
        0xC800,
        "the extended transport protocol's connection management (ETP.CM)",
    ),
    (0xEA00, "Request, which hwgw's address claiming answers"),
    (
        0xEE00,
        "Address Claimed, which hwgw's address claiming handles",
    ),
];

/// The card's node, if it claims an address.
pub(super) fn node(config: &J1939Config) -> Result<Option<J1939Node>, MapError> {
    match (config.name, config.address) {
        (None, None) => Ok(None),
        (Some(0), Some(_)) => Err(bad(
            "j1939.name",
            "NAME 0 is the kernel's \"no NAME\": give the node's NAME (J1939-81)",
        )),
        (Some(name), Some(address)) if address <= LAST_ADDRESS => Ok(Some(J1939Node {
            name: Name(name),
            address,
        })),
        (Some(_), Some(a)) => Err(bad(
            "j1939.address",
            format!("{a:#x}: expected a source address from 0 to {LAST_ADDRESS:#x}"),
        )),
        (Some(_), None) => Err(bad(
            "j1939",
            "a NAME needs the address to claim with it (address = …)",
        )),
        (None, Some(_)) => Err(bad(
            "j1939",
            "an address is claimed with a NAME (name = \"0x…\", J1939-81)",
        )),
    }
}

/// The J1939 side of frame `f` at `path` (its id, whether extended, its length), none
/// when it is a plain CAN frame.
pub(super) fn frame(
    config: &CanConfig,
    f: &FrameConfig,
    path: &str,
    (id, extended, length): (u32, bool, usize),
    tx: bool,
) -> Result<Option<J1939Frame>, MapError> {
    let keys = [
        ("source", f.source.is_some()),
        ("priority", f.priority.is_some()),
        ("destination", f.destination.is_some()),
    ];
    let Some(j) = config.j1939.as_ref().filter(|_| extended) else {
        if let Some((key, _)) = keys.iter().find(|(_, set)| *set) {
            return Err(bad(
                format!("{path}.{key}"),
                "only J1939 frames have one: an extended frame on a card with a [j1939] table",
            ));
        }
        return Ok(None);
    };
    let p = parts(id);
    if let Some((_, what)) = RESERVED.iter().find(|(pgn, _)| *pgn == p.pgn.0) {
        return Err(bad(
            path,
            format!("PGN {} is {what}: it cannot be mapped", p.pgn),
        ));
    }
    if f.fd == Some(true) {
        return Err(bad(
            format!("{path}.fd"),
            "J1939 groups go in classic frames (the kernel's J1939 stack has no FD)",
        ));
    }
    let most = if tx {
        MAX_SENT
    } else {
        crate::signal::MAX_PAYLOAD
    };
    if length > most {
        return Err(bad(
            format!("{path}.length"),
            if tx {
                format!(
                    "{length} bytes: hwgw sends J1939 groups of up to {MAX_SENT} bytes (TP); longer ones (ETP) it only receives"
                )
            } else {
                format!("{length} bytes: hwgw maps J1939 groups of up to {most} bytes")
            },
        ));
    }
    if let Some(pr) = f.priority.filter(|&pr| pr > 7) {
        return Err(bad(
            format!("{path}.priority"),
            format!("{pr}: a J1939 priority is 0 (highest) to 7"),
        ));
    }
    if !tx {
        if f.destination.is_some() {
            return Err(bad(
                format!("{path}.destination"),
                "a received group is matched whatever its destination; destination is for sent ones",
            ));
        }
        return Ok(Some(J1939Frame {
            pgn: p.pgn,
            source: f.source,
            priority: f.priority,
            destination: GLOBAL,
        }));
    }
    if f.source.is_some() {
        return Err(bad(
            format!("{path}.source"),
            "a sent group goes from the card's claimed address (j1939.address)",
        ));
    }
    if j.name.is_none() {
        return Err(bad(
            path,
            "sending J1939 needs an address: set name and address in the [j1939] table",
        ));
    }
    let priority = f.priority.unwrap_or(p.priority);
    if priority < 2 {
        return Err(bad(
            if f.priority.is_some() {
                format!("{path}.priority")
            } else {
                path.to_string()
            },
            format!(
                "priority {priority}: the kernel sends priorities 0 and 1 only for CAP_NET_ADMIN, which hwgw's service does not have; set priority = 2 to 7"
            ),
        ));
    }
    let destination = match f.destination {
        Some(_) if !p.pgn.is_pdu1() => {
            return Err(bad(
                format!("{path}.destination"),
                format!("PGN {} is a PDU2 group: it is always broadcast", p.pgn),
            ));
        }
        Some(d) => d,
        None => p.destination,
    };
    Ok(Some(J1939Frame {
        pgn: p.pgn,
        source: None,
        priority: Some(priority),
        destination,
    }))
}

/// Where `frame` is mapped already among `same` (frames of its direction), by what matches
/// it: a J1939 group by PGN and pinned source (rx) or destination (tx), else the id.
pub(super) fn clash(same: &[MappedFrame], frame: &MappedFrame) -> Option<(usize, String)> {
    same.iter()
        .enumerate()
        .find_map(|(k, o)| match (o.j1939, frame.j1939) {
            (Some(a), Some(b))
                if a.pgn == b.pgn && a.source == b.source && a.destination == b.destination =>
            {
                Some((
                    k,
                    match b.source {
                        Some(s) => format!("PGN {} from {s:#x}", b.pgn),
                        None => format!("PGN {}", b.pgn),
                    },
                ))
            }
            (None, None) if o.id == frame.id && o.extended == frame.extended => {
                Some((k, format!("id {:#x}", frame.id)))
            }
            _ => None,
        })
}
