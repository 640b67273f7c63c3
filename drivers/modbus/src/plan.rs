//! Request planning: as few reads as the protocol allows for a card's register map.
//!
//! Every point of a map is a [`Span`] of one table. Spans of a table that are contiguous,
//! overlap, or lie at most `max_gap` addresses apart are coalesced into one read, as long as
//! the read stays within the protocol's limit (125 registers for function codes 3 and 4,
//! 2000 bits for 1 and 2). A span is never split across reads, so a 32-bit value always
//! arrives whole. Reading a few unused registers in a gap costs far less than another
//! round trip, but some devices refuse reads of unmapped addresses: `max_gap = 0` reads
//! only what is mapped.
//!
//! ```
//! use driver_modbus::plan::{plan, Span, Table};
//!
//! let spans = [
//!     Span { table: Table::HoldingRegisters, address: 100, count: 2 },
//!     Span { table: Table::HoldingRegisters, address: 102, count: 1 },
//!     Span { table: Table::HoldingRegisters, address: 110, count: 2 },
//!     Span { table: Table::Coils, address: 0, count: 1 },
//! ];
//! let reads = plan(&spans, 8)?;
//! assert_eq!(reads.len(), 2); // holding 100..=111 in one read, coil 0 in another
//! assert_eq!(reads[1].to_string(), "FC3 read holding registers 100..=111 (12) for points [0, 1, 2]");
//! # Ok::<(), driver_modbus::plan::PlanError>(())
//! ```

use serde::Deserialize;
use std::fmt;

/// The four Modbus data tables.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Table {
    /// Read-write bits (function codes 1, 5, 15).
    Coils,
    /// Read-only bits (function code 2).
    DiscreteInputs,
    /// Read-only registers (function code 4).
    InputRegisters,
    /// Read-write registers (function codes 3, 6, 16).
    HoldingRegisters,
}

impl fmt::Display for Table {
    /// The table's name as a configuration writes it (`holding_registers`).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Table::Coils => "coils",
            Table::DiscreteInputs => "discrete_inputs",
            Table::InputRegisters => "input_registers",
            Table::HoldingRegisters => "holding_registers",
        })
    }
}

impl Table {
    /// The most one read may ask for: 2000 bits or 125 registers.
    pub fn max_read(self) -> u16 {
        if self.is_bits() { 2000 } else { 125 }
    }

    /// True for the bit tables.
    pub fn is_bits(self) -> bool {
        matches!(self, Table::Coils | Table::DiscreteInputs)
    }

    /// The function code that reads the table.
    pub fn read_function(self) -> u8 {
        match self {
            Table::Coils => 1,
            Table::DiscreteInputs => 2,
            Table::HoldingRegisters => 3,
            Table::InputRegisters => 4,
        }
    }

    /// Its name: "holding registers".
    pub fn name(self) -> &'static str {
        match self {
            Table::Coils => "coils",
            Table::DiscreteInputs => "discrete inputs",
            Table::InputRegisters => "input registers",
            Table::HoldingRegisters => "holding registers",
        }
    }
}

/// What one point of a map occupies: `count` addresses from `address` in `table`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Span {
    /// The table.
    pub table: Table,
    /// First address (0-based, as on the wire).
    pub address: u16,
    /// Number of registers or bits.
    pub count: u16,
}

/// One read of the plan.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Read {
    /// The table.
    pub table: Table,
    /// First address.
    pub start: u16,
    /// Registers or bits to read.
    pub count: u16,
    /// Indices of the spans (points) it serves, ascending.
    pub points: Vec<usize>,
}

impl fmt::Display for Read {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "FC{} read {} {}..={} ({}) for points {:?}",
            self.table.read_function(),
            self.table.name(),
            self.start,
            u32::from(self.start) + u32::from(self.count) - 1,
            self.count,
            self.points
        )
    }
}

/// Why a map cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PlanError {
    /// A span of zero addresses.
    #[error("point {point}: it covers no address")]
    Empty {
        /// The point.
        point: usize,
    },
    /// A span past address 65535.
    #[error("point {point}: addresses {address}..{end} run past 65535")]
    PastEnd {
        /// The point.
        point: usize,
        /// Its first address.
        address: u16,
        /// One past its last address.
        end: u32,
    },
    /// A span longer than one read may be.
    #[error("point {point}: {count} {} is more than one read may carry ({max})", if *.bits { "bits" } else { "registers" })]
    TooLong {
        /// The point.
        point: usize,
        /// Its length.
        count: u16,
        /// The limit.
        max: u16,
        /// A bit table.
        bits: bool,
    },
}

impl PlanError {
    /// The same error with its point index mapped through `f` (for callers that plan a
    /// subset of their points).
    pub fn renumber(self, f: impl Fn(usize) -> usize) -> Self {
        match self {
            PlanError::Empty { point } => PlanError::Empty { point: f(point) },
            PlanError::PastEnd {
                point,
                address,
                end,
            } => PlanError::PastEnd {
                point: f(point),
                address,
                end,
            },
            PlanError::TooLong {
                point,
                count,
                max,
                bits,
            } => PlanError::TooLong {
                point: f(point),
                count,
                max,
                bits,
            },
        }
    }
}

/// Unmapped addresses `from..to` of `table` between two spans, of which the unit refuses
/// at least one: no read may cover them (a unit's learned holes; see
/// [`holes`](crate::holes)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Barrier {
    /// The table.
    pub table: Table,
    /// First unmapped address of the gap.
    pub from: u32,
    /// One past its last (the next span's first address).
    pub to: u32,
}

/// Barriers written one after the other, comma-separated, without building a string (a
/// log record formats it in place).
pub(crate) struct Listed<'a>(pub(crate) &'a [Barrier]);

impl fmt::Display for Listed<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, b) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(", ")?;
            }
            write!(f, "{b}")?;
        }
        Ok(())
    }
}

impl fmt::Display for Barrier {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}..={}", self.table.name(), self.from, self.to - 1)
    }
}

/// The reads that cover every span, coalescing spans at most `max_gap` addresses apart
/// within the protocol's limits. Reads are ordered by table, then address.
pub fn plan(spans: &[Span], max_gap: u16) -> Result<Vec<Read>, PlanError> {
    plan_around(spans, max_gap, &[])
}

/// As [`plan`], never reading across a gap that holds one of `barriers`. Greedy from the
/// lowest address, which is the fewest reads: no read may be longer than the protocol's
/// limit nor cross a barrier, and taking each span into the read under way whenever it
/// may never needs more reads than cutting earlier.
pub fn plan_around(
    spans: &[Span],
    max_gap: u16,
    barriers: &[Barrier],
) -> Result<Vec<Read>, PlanError> {
    for (i, s) in spans.iter().enumerate() {
        let end = u32::from(s.address) + u32::from(s.count);
        if s.count == 0 {
            return Err(PlanError::Empty { point: i });
        }
        if end > 65536 {
            return Err(PlanError::PastEnd {
                point: i,
                address: s.address,
                end,
            });
        }
        if s.count > s.table.max_read() {
            return Err(PlanError::TooLong {
                point: i,
                count: s.count,
                max: s.table.max_read(),
                bits: s.table.is_bits(),
            });
        }
    }
    let mut order: Vec<usize> = (0..spans.len()).collect();
    order.sort_by_key(|&i| {
        (
            spans[i].table,
            spans[i].address,
            std::cmp::Reverse(spans[i].count),
        )
    });
    let mut reads: Vec<Read> = Vec::new();
    for i in order {
        let s = spans[i];
        let (start, end) = (
            u32::from(s.address),
            u32::from(s.address) + u32::from(s.count),
        ); // end exclusive
        if let Some(r) = reads.last_mut()
            && r.table == s.table
        {
            let r_end = u32::from(r.start) + u32::from(r.count);
            let new_end = r_end.max(end);
            let near = start <= r_end + u32::from(max_gap);
            let blocked = start > r_end
                && barriers
                    .iter()
                    .any(|b| b.table == s.table && b.from < start && r_end < b.to);
            if near && !blocked && new_end - u32::from(r.start) <= u32::from(s.table.max_read()) {
                // Fits: checked against max_read (<= 2000) just above.
                r.count = (new_end - u32::from(r.start)) as u16;
                r.points.push(i);
                continue;
            }
        }
        reads.push(Read {
            table: s.table,
            start: s.address,
            count: s.count,
            points: vec![i],
        });
    }
    for r in &mut reads {
        r.points.sort_unstable();
    }
    Ok(reads)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hr(address: u16, count: u16) -> Span {
        Span {
            table: Table::HoldingRegisters,
            address,
            count,
        }
    }

    #[test]
    fn contiguous_and_overlapping_spans_merge() {
        let reads = plan(&[hr(10, 2), hr(12, 1), hr(12, 1), hr(13, 4)], 0).unwrap();
        assert_eq!(
            reads,
            vec![Read {
                table: Table::HoldingRegisters,
                start: 10,
                count: 7,
                points: vec![0, 1, 2, 3]
            }]
        );
    }

    #[test]
    fn the_gap_threshold_decides() {
        let spans = [hr(0, 1), hr(5, 1)];
        assert_eq!(
            plan(&spans, 3).unwrap().len(),
            2,
            "4 unused registers in between > 3"
        );
        assert_eq!(plan(&spans, 4).unwrap().len(), 1);
        assert_eq!(plan(&spans, 4).unwrap()[0].count, 6);
    }

    #[test]
    fn reads_stay_within_the_protocol_limits_and_never_split_a_value() {
        // 63 two-register values back to back: 126 registers, one more than a read carries.
        let spans: Vec<Span> = (0..63).map(|i| hr(i * 2, 2)).collect();
        let reads = plan(&spans, 0).unwrap();
        assert_eq!(reads.len(), 2);
        assert_eq!(
            (reads[0].start, reads[0].count),
            (0, 124),
            "62 whole values, not 125 registers with half a value"
        );
        assert_eq!((reads[1].start, reads[1].count), (124, 2));
        let coils: Vec<Span> = (0..2001)
            .map(|a| Span {
                table: Table::Coils,
                address: a,
                count: 1,
            })
            .collect();
        let reads = plan(&coils, 0).unwrap();
        assert_eq!(
            reads.iter().map(|r| r.count).collect::<Vec<_>>(),
            vec![2000, 1]
        );
    }

    #[test]
    fn tables_are_read_separately() {
        let spans = [
            Span {
                table: Table::InputRegisters,
                address: 0,
                count: 1,
            },
            hr(0, 1),
            Span {
                table: Table::DiscreteInputs,
                address: 0,
                count: 1,
            },
            Span {
                table: Table::Coils,
                address: 1,
                count: 1,
            },
        ];
        let fcs: Vec<u8> = plan(&spans, 100)
            .unwrap()
            .iter()
            .map(|r| r.table.read_function())
            .collect();
        assert_eq!(fcs, vec![1, 2, 4, 3]);
    }

    #[test]
    fn bad_spans_are_errors() {
        assert_eq!(
            plan(&[hr(0, 0)], 0).unwrap_err(),
            PlanError::Empty { point: 0 }
        );
        assert_eq!(
            plan(&[hr(1, 1), hr(65535, 2)], 0).unwrap_err().to_string(),
            "point 1: addresses 65535..65537 run past 65535"
        );
        assert_eq!(
            plan(&[hr(0, 126)], 0).unwrap_err().to_string(),
            "point 0: 126 registers is more than one read may carry (125)"
        );
        assert!(plan(&[hr(65535, 1)], 0).is_ok());
    }

    /// Random maps: every point is covered whole by exactly one read that names it, reads
    /// respect the limits, and no read carries a gap wider than allowed.
    #[test]
    fn random_maps_keep_every_promise() {
        let mut seed = 0x1234_5678_u64;
        let mut next = |m: u64| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) % m
        };
        for _ in 0..300 {
            let gap = next(40) as u16;
            let n = 1 + next(200) as usize;
            let spans: Vec<Span> = (0..n)
                .map(|_| {
                    let table = [
                        Table::Coils,
                        Table::DiscreteInputs,
                        Table::InputRegisters,
                        Table::HoldingRegisters,
                    ][next(4) as usize];
                    let count = if table.is_bits() {
                        1
                    } else {
                        [1, 2, 4][next(3) as usize]
                    };
                    Span {
                        table,
                        address: next(3000) as u16,
                        count,
                    }
                })
                .collect();
            let reads = plan(&spans, gap).unwrap();
            let mut served = vec![0; n];
            for r in &reads {
                assert!(r.count <= r.table.max_read());
                let (rs, re) = (u32::from(r.start), u32::from(r.start) + u32::from(r.count));
                let mut covered: Vec<(u32, u32)> = Vec::new();
                for &p in &r.points {
                    let s = spans[p];
                    let (ss, se) = (
                        u32::from(s.address),
                        u32::from(s.address) + u32::from(s.count),
                    );
                    assert!(
                        s.table == r.table && rs <= ss && se <= re,
                        "point {p} {s:?} not inside {r}"
                    );
                    served[p] += 1;
                    covered.push((ss, se));
                }
                covered.sort_unstable();
                assert_eq!(
                    covered.first().map(|c| c.0),
                    Some(rs),
                    "a read starts at a point"
                );
                let mut reach = rs;
                for (ss, se) in covered {
                    assert!(
                        ss <= reach + u32::from(gap),
                        "gap {}..{ss} wider than {gap} in {r}",
                        reach
                    );
                    reach = reach.max(se);
                }
                assert_eq!(reach, re, "a read ends at a point");
            }
            assert!(
                served.iter().all(|&c| c == 1),
                "every point in exactly one read"
            );
        }
    }
}
