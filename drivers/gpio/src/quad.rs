//! Software quadrature decoding: the motion two square waves 90° apart (A, B) describe,
//! from their edges one at a time.
//!
//! Every edge counts (x4 decoding: four counts per cycle of A). A leading B is the
//! positive direction. An edge that leaves its line at the level it already had, or that
//! would take both lines one step at once, means events were lost: it is counted as an
//! error and the decoder takes the new level without guessing a motion.
//!
//! ```
//! use driver_gpio::quad::{Quadrature, Step};
//!
//! let mut q = Quadrature::new(false, false);
//! // A leads B: A up, B up, A down, B down is one cycle forward.
//! let steps: Vec<Step> = [(0, true), (1, true), (0, false), (1, false)]
//!     .into_iter()
//!     .map(|(line, level)| q.edge(line, level))
//!     .collect();
//! assert!(steps.iter().all(|s| *s == Step::Moved(1)));
//! assert_eq!(q.edge(1, true), Step::Moved(-1)); // B leads now: backwards
//! assert_eq!(q.edge(1, true), Step::Error);     // B was already high: an edge was lost
//! ```

/// What one edge did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// Moved by one count (+1 or -1).
    Moved(i64),
    /// An impossible transition: events were lost.
    Error,
}

/// The decoder's state: the levels of A and B.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Quadrature {
    a: bool,
    b: bool,
}

/// Position of (A, B) in the forward cycle 00 → 10 → 11 → 01.
fn phase(a: bool, b: bool) -> i64 {
    match (a, b) {
        (false, false) => 0,
        (true, false) => 1,
        (true, true) => 2,
        (false, true) => 3,
    }
}

impl Quadrature {
    /// A decoder whose lines are at these levels now.
    pub fn new(a: bool, b: bool) -> Quadrature {
        Quadrature { a, b }
    }

    /// Line 0 (A) or 1 (B) is now at `level`.
    pub fn edge(&mut self, line: u8, level: bool) -> Step {
        let (a, b) = if line == 0 {
            (level, self.b)
        } else {
            (self.a, level)
        };
        let before = phase(self.a, self.b);
        self.a = a;
        self.b = b;
        match (phase(a, b) - before).rem_euclid(4) {
            1 => Step::Moved(1),
            3 => Step::Moved(-1),
            // 0: the line did not change (its other edge was lost); 2 cannot come from
            // one line's edge, but is an error all the same.
            _ => Step::Error,
        }
    }

    /// The levels of (A, B) as the decoder has them.
    pub fn levels(&self) -> (bool, bool) {
        (self.a, self.b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn many_cycles_both_ways_count_exactly() {
        let mut q = Quadrature::new(false, false);
        let forward = [(0, true), (1, true), (0, false), (1, false)];
        let mut total = 0;
        for _ in 0..1000 {
            for (l, v) in forward {
                let Step::Moved(d) = q.edge(l, v) else {
                    panic!("error going forward")
                };
                total += d;
            }
        }
        assert_eq!(total, 4000);
        for _ in 0..250 {
            for (l, v) in forward.iter().rev() {
                // Backwards: undo each edge in reverse order.
                let Step::Moved(d) = q.edge(*l, !*v) else {
                    panic!("error going back")
                };
                total += d;
            }
        }
        assert_eq!(total, 3000);
        assert_eq!(q.levels(), (false, false));
    }
}
