//! A PDO's configuration (CiA 301 §7.5.2.35-38): which objects a node's RPDO or TPDO
//! carries and how it is sent, checked against the node's object dictionary, and the SDO
//! writes that set it in the procedure CiA 301 gives — the PDO made invalid (bit 31 of
//! its COB-ID), its transmission type and timers written, its mapping emptied, the
//! entries written, their count set, the PDO made valid with its COB-ID.
//!
//! Checks, each error naming the PDO and the object: the communication and mapping
//! objects exist (0x1400/0x1600 + n − 1 for RPDO n, 0x1800/0x1A00 for TPDO n) with the
//! sub-indices written; every mapped object exists, may be mapped, is writable (an RPDO's)
//! or readable (a TPDO's), and is mapped with its data type's length; at most 64 bits;
//! the COB-ID is an 11-bit id.

use crate::eds::{Access, ObjectDictionary, data_type};

/// Which way a PDO goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Received by the node (hwgw's outputs).
    Rpdo,
    /// Sent by the node (hwgw's inputs).
    Tpdo,
}

/// One mapped object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mapped {
    /// Index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Length, bits.
    pub bits: u8,
}

/// A PDO as the deployment wants it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pdo {
    /// RPDO or TPDO.
    pub direction: Direction,
    /// Its number, 1-512.
    pub number: u16,
    /// Its COB-ID (11 bits).
    pub cob_id: u16,
    /// Transmission type: 0 acyclic synchronous, 1-240 every n-th SYNC, 254/255 on event.
    pub transmission: u8,
    /// Event timer, ms (TPDOs sent on event; 0: none).
    pub event_timer_ms: Option<u16>,
    /// Inhibit time, multiples of 100 µs.
    pub inhibit_100us: Option<u16>,
    /// The objects it carries, in order.
    pub mapped: Vec<Mapped>,
}

/// One SDO write of the configuration.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Write {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Little-endian value.
    pub data: Vec<u8>,
}

/// Why a PDO configuration was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{pdo}: {why}")]
pub struct PdoError {
    /// The PDO, e.g. "TPDO1".
    pub pdo: String,
    /// What is wrong.
    pub why: String,
}

/// The bits of a CiA 301 basic type carried in a PDO (None: not a fixed-size type).
pub fn type_bits(t: u16) -> Option<u8> {
    use data_type::*;
    Some(match t {
        BOOLEAN => 1,
        INTEGER8 | UNSIGNED8 => 8,
        INTEGER16 | UNSIGNED16 => 16,
        0x10 | 0x16 => 24,
        INTEGER32 | UNSIGNED32 | REAL32 => 32,
        0x12 | 0x18 => 40,
        0x13 | 0x19 => 48,
        0x14 | 0x1A => 56,
        INTEGER64 | UNSIGNED64 | REAL64 => 64,
        _ => return None,
    })
}

impl Pdo {
    fn name(&self) -> String {
        let d = match self.direction {
            Direction::Rpdo => "RPDO",
            Direction::Tpdo => "TPDO",
        };
        format!("{d}{}", self.number)
    }

    /// The communication and mapping objects' indices.
    pub fn objects(&self) -> (u16, u16) {
        let n = self.number.saturating_sub(1);
        match self.direction {
            Direction::Rpdo => (0x1400 + n, 0x1600 + n),
            Direction::Tpdo => (0x1800 + n, 0x1A00 + n),
        }
    }

    /// The SDO writes that configure it on a node with dictionary `od`, in order.
    pub fn writes(&self, od: &ObjectDictionary) -> Result<Vec<Write>, PdoError> {
        let fail = |why: String| PdoError {
            pdo: self.name(),
            why,
        };
        if !(1..=512).contains(&self.number) {
            return Err(fail(format!("number {}: expected 1 to 512", self.number)));
        }
        if self.cob_id == 0 || self.cob_id > 0x7FF {
            return Err(fail(format!(
                "COB-ID {:#x}: expected 0x001 to 0x7FF",
                self.cob_id
            )));
        }
        let (comm, map) = self.objects();
        let has = |index: u16, sub: u8| od.variable(index, sub).is_some();
        for (index, sub) in [(comm, 1), (comm, 2), (map, 0)] {
            if !has(index, sub) {
                return Err(fail(format!("the node has no {index:#06x} sub {sub}")));
            }
        }
        let mut total = 0u32;
        for (k, m) in self.mapped.iter().enumerate() {
            let entry = k as u8 + 1;
            if !has(map, entry) {
                return Err(fail(format!(
                    "{} objects mapped: the node's {map:#06x} has no sub {entry}",
                    self.mapped.len()
                )));
            }
            let Some(v) = od.variable(m.index, m.sub) else {
                return Err(fail(format!(
                    "{:#06x} sub {} is not in the node's dictionary",
                    m.index, m.sub
                )));
            };
            if !v.pdo_mappable {
                return Err(fail(format!(
                    "{:#06x} sub {} ({}) may not be mapped",
                    m.index, m.sub, v.name
                )));
            }
            let usable = match self.direction {
                Direction::Rpdo => matches!(v.access, Access::Rw | Access::Rww | Access::Wo),
                Direction::Tpdo => matches!(
                    v.access,
                    Access::Ro | Access::Rw | Access::Rwr | Access::Const
                ),
            };
            if !usable {
                return Err(fail(format!(
                    "{:#06x} sub {} ({}) is {}: an {} carries what it may {}",
                    m.index,
                    m.sub,
                    v.name,
                    v.access.as_str(),
                    self.name().trim_end_matches(char::is_numeric),
                    if self.direction == Direction::Rpdo {
                        "write"
                    } else {
                        "read"
                    }
                )));
            }
            match type_bits(v.data_type) {
                Some(b) if b == m.bits => {}
                Some(b) => {
                    return Err(fail(format!(
                        "{:#06x} sub {} ({}) is {b} bits, mapped as {}",
                        m.index, m.sub, v.name, m.bits
                    )));
                }
                None => {
                    return Err(fail(format!(
                        "{:#06x} sub {} ({}) has no fixed size to map",
                        m.index, m.sub, v.name
                    )));
                }
            }
            total += u32::from(m.bits);
        }
        if total > 64 {
            return Err(fail(format!(
                "{total} bits mapped: a PDO carries at most 64"
            )));
        }
        let u32le = |v: u32| v.to_le_bytes().to_vec();
        let w = |index: u16, sub: u8, data: Vec<u8>| Write { index, sub, data };
        let mut out = vec![
            w(comm, 1, u32le(0x8000_0000 | u32::from(self.cob_id))),
            w(comm, 2, vec![self.transmission]),
        ];
        if let Some(t) = self.inhibit_100us {
            if !has(comm, 3) {
                return Err(fail(format!(
                    "the node has no {comm:#06x} sub 3 (inhibit time)"
                )));
            }
            out.push(w(comm, 3, t.to_le_bytes().to_vec()));
        }
        if let Some(t) = self.event_timer_ms {
            if !has(comm, 5) {
                return Err(fail(format!(
                    "the node has no {comm:#06x} sub 5 (event timer)"
                )));
            }
            out.push(w(comm, 5, t.to_le_bytes().to_vec()));
        }
        out.push(w(map, 0, vec![0]));
        for (k, m) in self.mapped.iter().enumerate() {
            let entry = (u32::from(m.index) << 16) | (u32::from(m.sub) << 8) | u32::from(m.bits);
            out.push(w(map, k as u8 + 1, u32le(entry)));
        }
        out.push(w(map, 0, vec![self.mapped.len() as u8]));
        out.push(w(comm, 1, u32le(u32::from(self.cob_id))));
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    const IO: &str = include_str!("../tests/eds/io401.eds");

    fn tpdo(mapped: Vec<Mapped>) -> Pdo {
        Pdo {
            direction: Direction::Tpdo,
            number: 1,
            cob_id: 0x185,
            transmission: 255,
            event_timer_ms: Some(50),
            inhibit_100us: None,
            mapped,
        }
    }

    #[test]
    fn the_writes_follow_cia_301s_procedure() {
        let od = crate::eds::parse(IO, Some(5)).unwrap();
        let m = |index, sub, bits| Mapped { index, sub, bits };
        let w = tpdo(vec![m(0x6000, 1, 8), m(0x6401, 1, 16)])
            .writes(&od)
            .unwrap();
        let cmds: Vec<(u16, u8, Vec<u8>)> =
            w.into_iter().map(|w| (w.index, w.sub, w.data)).collect();
        assert_eq!(
            cmds,
            vec![
                (0x1800, 1, vec![0x85, 0x01, 0, 0x80]),
                (0x1800, 2, vec![255]),
                (0x1800, 5, vec![50, 0]),
                (0x1A00, 0, vec![0]),
                (0x1A00, 1, vec![0x08, 0x01, 0x00, 0x60]),
                (0x1A00, 2, vec![0x10, 0x01, 0x01, 0x64]),
                (0x1A00, 0, vec![2]),
                (0x1800, 1, vec![0x85, 0x01, 0, 0]),
            ]
        );
    }

    #[test]
    fn what_the_node_cannot_carry_is_refused_by_name() {
        let od = crate::eds::parse(IO, Some(5)).unwrap();
        let m = |index, sub, bits| Mapped { index, sub, bits };
        let err = |p: Pdo| p.writes(&od).unwrap_err().to_string();
        assert_eq!(
            err(tpdo(vec![m(0x6401, 1, 8)])),
            "TPDO1: 0x6401 sub 1 (Analog input 1) is 16 bits, mapped as 8"
        );
        assert_eq!(
            err(tpdo(vec![m(0x1017, 0, 16)])),
            "TPDO1: 0x1017 sub 0 (Producer heartbeat time) may not be mapped"
        );
        assert_eq!(
            err(tpdo(vec![
                m(0x6000, 1, 8),
                m(0x6401, 1, 16),
                m(0x6401, 2, 16)
            ])),
            "TPDO1: 3 objects mapped: the node's 0x1a00 has no sub 3"
        );
        let rpdo = Pdo {
            direction: Direction::Rpdo,
            cob_id: 0x205,
            ..tpdo(vec![m(0x6000, 1, 8)])
        };
        assert_eq!(
            err(Pdo {
                event_timer_ms: None,
                ..rpdo
            }),
            "RPDO1: 0x6000 sub 1 (Read input 1h to 8h) is ro: an RPDO carries what it may write"
        );
        assert_eq!(
            err(Pdo {
                number: 2,
                ..tpdo(vec![])
            }),
            "TPDO2: the node has no 0x1801 sub 1"
        );
    }
}
