//! Units that refuse reads over unmapped addresses: which gaps of a refused read hold the
//! addresses a unit does not have, found by reading parts of it, and the barriers the
//! unit's plan is then made around ([`Map::reads_around`]).
//!
//! The points of a read, in address order, leave gaps between them; a unit that answers
//! the read with IllegalDataAddress has a hole in at least one gap (a read of mapped
//! addresses only is the unit's answer about the map itself, not a hole). A part of the
//! read — the points on either side of a range of its gaps — read whole tells that none of
//! those gaps holds a hole. Halving the refused ranges finds every gap that holds one in
//! about 2·log2(gaps) reads a hole, made once per unit. A unit that refuses a read but takes
//! both its halves (a read limit of its own) has the read cut between them. The gaps found
//! become [`Barrier`]s: the plan made anew around them is as few reads as the holes allow.

use crate::map::Map;
use crate::plan::{Barrier, Read};

/// A read's points in address order and the gaps between them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Gaps {
    /// The read's points (indices into the map's points), by address.
    points: Vec<usize>,
    /// Each gap: the index in `points` of the point after it, and its addresses.
    gaps: Vec<(usize, Barrier)>,
}

impl Gaps {
    /// The gaps of `read` over `map`'s points.
    pub fn of(map: &Map, read: &Read) -> Gaps {
        let span = |p: usize| {
            map.points().get(p).map_or((0, 0), |x| {
                let s = u32::from(x.span.address);
                (s, s + u32::from(x.span.count))
            })
        };
        let mut points = read.points.clone();
        points.sort_by_key(|&p| span(p));
        let mut gaps = Vec::new();
        let mut reach = None;
        for (k, &p) in points.iter().enumerate() {
            let (start, end) = span(p);
            if let Some(r) = reach
                && start > r
            {
                let barrier = Barrier {
                    table: read.table,
                    from: r,
                    to: start,
                };
                gaps.push((k, barrier));
            }
            reach = Some(reach.map_or(end, |r: u32| r.max(end)));
        }
        Gaps { points, gaps }
    }

    /// How many gaps.
    pub fn len(&self) -> usize {
        self.gaps.len()
    }

    /// True when the read's points leave no gap.
    pub fn is_empty(&self) -> bool {
        self.gaps.is_empty()
    }

    /// The read of the points around gaps `first..=last` (from the point before the first
    /// to the point after the last): it covers those gaps and no other.
    pub fn part(&self, map: &Map, read: &Read, first: usize, last: usize) -> Read {
        let lo = self.gaps.get(first).map_or(0, |g| g.0.saturating_sub(1));
        let hi = self.gaps.get(last).map_or(0, |g| g.0);
        let points = self.points.get(lo..=hi).unwrap_or_default();
        let span = |p: &usize| map.points().get(*p).map(|x| x.span);
        let start = points
            .iter()
            .filter_map(span)
            .map(|s| u32::from(s.address))
            .min()
            .unwrap_or(0);
        let end = points
            .iter()
            .filter_map(span)
            .map(|s| u32::from(s.address) + u32::from(s.count))
            .max()
            .unwrap_or(start);
        let mut pts = points.to_vec();
        pts.sort_unstable();
        // Within the refused read, which is within the protocol's limits.
        Read {
            table: read.table,
            start: start as u16,
            count: (end - start) as u16,
            points: pts,
        }
    }
}

/// Finds the gaps of `read` (refused with IllegalDataAddress) that hold holes, asking
/// `accepts` whether the unit takes a part of the read (`Ok(false)`: refused with
/// IllegalDataAddress; `Err`: any other failure, which ends the search). Every gap found,
/// at least one when the read has any.
pub async fn find<E>(
    map: &Map,
    read: &Read,
    mut accepts: impl AsyncFnMut(&Read) -> Result<bool, E>,
) -> Result<Vec<Barrier>, E> {
    let g = Gaps::of(map, read);
    let mut found = Vec::new();
    if g.is_empty() {
        return Ok(found);
    }
    // Ranges of gaps a refused read covers.
    let mut refused = vec![(0, g.len() - 1)];
    while let Some((i, j)) = refused.pop() {
        if i == j {
            found.push(g.gaps[i].1);
            continue;
        }
        let mid = (i + j) / 2;
        let left = accepts(&g.part(map, read, i, mid)).await?;
        let right = accepts(&g.part(map, read, mid + 1, j)).await?;
        if !left {
            refused.push((i, mid));
        }
        if !right {
            refused.push((mid + 1, j));
        }
        if left && right {
            // Each half taken, the whole refused: the unit limits its reads; cut there.
            found.push(g.gaps[mid].1);
        }
    }
    found.sort_by_key(|b| (b.from, b.to));
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::PointConfig;
    use crate::plan::Table;
    use std::collections::BTreeSet;

    fn map(addresses: &[u16]) -> Map {
        let text: String = addresses
            .iter()
            .map(|a| format!("[[point]]\ntable = \"input_registers\"\naddress = {a}\n"))
            .collect();
        let t: toml::Table = toml::from_str(&text).unwrap_or_default();
        let points: Vec<PointConfig> = t
            .get("point")
            .cloned()
            .and_then(|p| p.try_into().ok())
            .unwrap_or_default();
        match Map::new(&points, crate::map::ANY_GAP) {
            Ok(m) => m,
            Err(e) => panic!("{e}"),
        }
    }

    /// A unit without the addresses `holes`: does it take `r`?
    fn unit(holes: &BTreeSet<u32>, r: &Read, asked: &mut Vec<String>) -> bool {
        asked.push(r.to_string());
        let (s, e) = (u32::from(r.start), u32::from(r.start) + u32::from(r.count));
        holes.range(s..e).next().is_none()
    }

    fn learn(addresses: &[u16], holes: &[u32]) -> (usize, Vec<Read>, Vec<String>) {
        let m = map(addresses);
        let holes: BTreeSet<u32> = holes.iter().copied().collect();
        let mut asked = Vec::new();
        let mut barriers = Vec::new();
        // As the line does: learn from every refused read until none is refused.
        loop {
            let reads = m.reads_around(&barriers);
            let Some(bad) = reads.iter().find(|r| !unit(&holes, r, &mut Vec::new())) else {
                return (barriers.len(), reads, asked);
            };
            let found = futures_lite(find(&m, bad, async |r: &Read| {
                Ok::<_, ()>(unit(&holes, r, &mut asked))
            }));
            let found = found.unwrap_or_default();
            assert!(!found.is_empty(), "a refused read with gaps has a hole");
            barriers.extend(found);
        }
    }

    /// Drives a future that never waits (the fake unit answers at once).
    fn futures_lite<T>(f: impl std::future::Future<Output = T>) -> T {
        let rt = tokio::runtime::Builder::new_current_thread().build();
        match rt {
            Ok(rt) => rt.block_on(f),
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn a_hole_in_one_gap_leaves_the_others_coalesced() {
        // Points at 0, 10, 100; a hole only at 5: two reads (0) and (10..=100).
        let (n, reads, _) = learn(&[0, 10, 100], &[5]);
        assert_eq!(n, 1);
        let r: Vec<String> = reads.iter().map(|r| r.to_string()).collect();
        assert_eq!(
            r,
            [
                "FC4 read input registers 0..=0 (1) for points [0]",
                "FC4 read input registers 10..=100 (91) for points [1, 2]",
            ]
        );
        // 0, 10, 20, 30 with a hole at 5 only: two reads, not three.
        let (_, reads, _) = learn(&[0, 10, 20, 30], &[5]);
        assert_eq!(reads.len(), 2);
    }

    #[test]
    fn every_hole_is_found_and_the_plan_is_the_fewest_reads() {
        // Random maps and holes: the plan reaches the minimum that reads around the holes
        // allow, counted independently (a cut at each gap that holds a hole, and wherever
        // a read would pass 125 registers), and no read of it is refused.
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = |n: u64| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed % n
        };
        for _ in 0..200 {
            let mut addresses: BTreeSet<u16> = BTreeSet::new();
            for _ in 0..1 + next(30) {
                addresses.insert(next(400) as u16);
            }
            let addresses: Vec<u16> = addresses.into_iter().collect();
            let mapped: BTreeSet<u32> = addresses.iter().map(|&a| u32::from(a)).collect();
            let holes: Vec<u32> = (0..next(6))
                .map(|_| next(400) as u32)
                .filter(|h| !mapped.contains(h))
                .collect();
            let (_, reads, asked) = learn(&addresses, &holes);
            let hs: BTreeSet<u32> = holes.iter().copied().collect();
            for r in &reads {
                assert!(unit(&hs, r, &mut Vec::new()), "{r} still refused");
            }
            // The minimum: greedy over the sorted points, cut at holes and the 125 limit.
            let mut min = 0;
            let mut start: Option<u32> = None;
            let mut last = 0u32;
            for &a in &addresses {
                let a = u32::from(a);
                let cut = match start {
                    None => true,
                    Some(s) => a + 1 - s > 125 || hs.range(last + 1..a).next().is_some(),
                };
                if cut {
                    min += 1;
                    start = Some(a);
                }
                last = a;
            }
            assert_eq!(
                reads.len(),
                min,
                "points {addresses:?}, holes {holes:?}: {reads:?}"
            );
            assert!(asked.len() <= 2 * addresses.len(), "{} probes", asked.len());
        }
    }

    #[test]
    fn a_unit_that_takes_both_halves_has_the_read_cut() {
        let m = map(&[0, 10, 20, 30]);
        let read = m.reads()[0].clone();
        let found = futures_lite(find(&m, &read, async |r: &Read| {
            // Refuses anything longer than 20 registers.
            Ok::<_, ()>(r.count <= 20)
        }));
        let found = found.unwrap_or_default();
        assert_eq!(
            found,
            [Barrier {
                table: Table::InputRegisters,
                from: 1,
                to: 10
            }]
        );
    }
}
