//! Telling a machine's stalls from a program's own: two periodic programs run in the same
//! seconds on the same CPU, and each late wake-up of one is set beside what the other did
//! while it waited. Used by the jitter bench's "together" piece; cyclictest's `--spike`
//! output gives its side's wake-up times.

/// A wake-up: when it was due and when it came, monotonic ns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Wake {
    /// When it was due.
    pub due: u64,
    /// When it came.
    pub woke: u64,
}

/// One program's late wake-ups, set against the other's ([`classify`]).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Seen {
    /// The other program's waits that overlapped this one lasted until about its end too:
    /// the CPU ran neither — the machine's stall.
    pub shared: u64,
    /// One of the other's overlapping waits ended well before this one's: the CPU was
    /// running the other program while this one waited — this program's own delay.
    pub alone: u64,
    /// None of the other's waits overlapped this one (the other was running or asleep
    /// until a grid point after it).
    pub not_compared: u64,
}

/// What the other program did while a late wake-up waited (see [`Seen`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// The CPU ran neither.
    Shared,
    /// The CPU ran the other program meanwhile.
    Alone,
    /// None of the other's waits overlapped.
    NotCompared,
}

/// How `w`, a wake-up more than `late_ns` late, stands against `other`'s wake-ups (in the
/// order they came, on the same CPU). Compared are those of the other's waits that overlap
/// `w`'s up to `late_ns` before its end: due by then and not come before `w` was due — one
/// due inside `w`'s wait, or one whose own wait had begun before it and was still going.
/// If any of them came more than `late_ns / 2` before `w`'s end, the CPU ran the other
/// program while `w` was due and had not run ([`Class::Alone`]) — even when a later one
/// waited until the end with it, since the first still shows a moment the CPU ran and
/// `w` did not: of the rules at hand, the one that blames a program most readily. If all
/// waited until about the same end, the CPU ran neither ([`Class::Shared`]).
pub fn class_of(w: Wake, other: &[Wake], late_ns: u64) -> Class {
    let first = other.partition_point(|o| o.woke < w.due);
    let end = w.woke.saturating_sub(late_ns);
    let mut overlapping = other[first..]
        .iter()
        .take_while(|o| o.due <= end)
        .peekable();
    if overlapping.peek().is_none() {
        Class::NotCompared
    } else if overlapping.any(|o| o.woke + late_ns / 2 < w.woke) {
        Class::Alone
    } else {
        Class::Shared
    }
}

/// Classifies each of `one`'s wake-ups more than `late_ns` late against `other`'s, by
/// [`class_of`].
pub fn classify(one: &[Wake], other: &[Wake], late_ns: u64) -> Seen {
    let mut seen = Seen::default();
    for &w in one
        .iter()
        .filter(|w| w.woke.saturating_sub(w.due) > late_ns)
    {
        match class_of(w, other, late_ns) {
            Class::Shared => seen.shared += 1,
            Class::Alone => seen.alone += 1,
            Class::NotCompared => seen.not_compared += 1,
        }
    }
    seen
}

/// What cyclictest's output could not be read as.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ReadError {
    /// No `-v` line: the run was not verbose, or printed nothing.
    #[error("cyclictest printed no latencies (`-v` lines)")]
    NoLatencies,
    /// A spike's latency is not that of the loop it was taken for.
    #[error(
        "cyclictest's loop {loop_} was {late} µs late by `-v`, but its spike {spike} says \
         {spike_late} µs"
    )]
    Mismatch {
        /// The loop, from 0.
        loop_: usize,
        /// Its latency by `-v`, µs.
        late: u64,
        /// The spike taken for it, from 0.
        spike: usize,
        /// That spike's latency, µs.
        spike_late: u64,
    },
    /// Not one spike for each loop over 1 µs late (`--spike-nodes` too small?).
    #[error("cyclictest printed {spikes} spikes for {late} loops over 1 µs late")]
    Count {
        /// Spikes printed.
        spikes: usize,
        /// Loops over 1 µs late.
        late: usize,
    },
}

/// cyclictest's `-v` lines, `       0:       0:      34` (thread, loop, latency µs): the
/// latencies in loop order.
pub fn cyclictest_latencies(text: &str) -> Vec<u64> {
    text.lines()
        .filter_map(|line| {
            let mut cols = line.split(':').map(str::trim);
            match (cols.next(), cols.next(), cols.next(), cols.next()) {
                (Some(t), Some(l), Some(us), None)
                    if t.parse::<u32>().is_ok() && l.parse::<u64>().is_ok() =>
                {
                    us.parse::<u64>().ok()
                }
                _ => None,
            }
        })
        .collect()
}

/// cyclictest's `--spike` records, `T: 0 Spike:      34: TS:  31547001284` (latency µs,
/// wake-up µs on its clock), as wake-ups in ns, in the order printed.
pub fn cyclictest_spikes(text: &str) -> Vec<Wake> {
    text.lines()
        .filter_map(|line| {
            let (_, rest) = line.split_once("Spike:")?;
            let (late, ts) = rest.split_once(": TS:")?;
            let late: u64 = late.trim().parse().ok()?;
            let ts: u64 = ts.trim().parse().ok()?;
            Some(Wake {
                due: ts.checked_sub(late)? * 1000,
                woke: ts * 1000,
            })
        })
        .collect()
}

/// Every wake-up of a one-thread cyclictest run with `-v --spike=1` and a period of
/// `period_ns`, in order, to the µs. A spike is recorded only for a wake-up over 1 µs
/// late; one that is missing was due at the grid point after the wake-up before it
/// (cyclictest moves its next due time on past a late wake-up) and came its `-v` latency
/// after it — or, before the first spike, as many periods before that one's.
pub fn cyclictest_wakes(text: &str, period_ns: u64) -> Result<Vec<Wake>, ReadError> {
    let late = cyclictest_latencies(text);
    let spikes = cyclictest_spikes(text);
    if late.is_empty() {
        return Err(ReadError::NoLatencies);
    }
    let recorded = late.iter().filter(|&&l| l > 1).count();
    if recorded != spikes.len() {
        return Err(ReadError::Count {
            spikes: spikes.len(),
            late: recorded,
        });
    }
    let mut wakes: Vec<Option<Wake>> = vec![None; late.len()];
    let mut spike = spikes.iter().enumerate();
    let mut before: Option<Wake> = None;
    for (k, &l) in late.iter().enumerate() {
        let w = if l > 1 {
            let (j, s) = spike.next().ok_or(ReadError::Count {
                spikes: spikes.len(),
                late: recorded,
            })?;
            let spike_late = (s.woke - s.due) / 1000;
            if spike_late != l {
                return Err(ReadError::Mismatch {
                    loop_: k,
                    late: l,
                    spike: j,
                    spike_late,
                });
            }
            Some(*s)
        } else {
            before.map(|b| {
                let mut due = b.due + period_ns;
                while due < b.woke {
                    due += period_ns;
                }
                Wake {
                    due,
                    woke: due + l * 1000,
                }
            })
        };
        wakes[k] = w;
        before = w.or(before);
    }
    // The loops before the first spike, each on time: a period apart, back from it.
    if let Some(first) = wakes.iter().position(Option::is_some) {
        let anchor = wakes[first].map_or(0, |w| w.due);
        for k in 0..first {
            let due = anchor.saturating_sub((first - k) as u64 * period_ns);
            wakes[k] = Some(Wake {
                due,
                woke: due + late[k] * 1000,
            });
        }
    }
    Ok(wakes.into_iter().flatten().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn w(due_us: u64, woke_us: u64) -> Wake {
        Wake {
            due: due_us * 1000,
            woke: woke_us * 1000,
        }
    }

    const LATE: u64 = 200_000;

    #[test]
    fn a_stall_of_both_is_shared_and_one_that_ran_the_other_is_alone() {
        // One due at 0 woke at 3000; the other's due at 500 and 1500 are inside the wait,
        // 2900 is too near its end to be compared.
        let one = [w(0, 3000)];
        let stalled = [w(500, 3010), w(1500, 3012), w(2900, 3014)];
        let s = classify(&one, &stalled, LATE);
        assert_eq!((s.shared, s.alone, s.not_compared), (1, 0, 0));
        let ran = [w(500, 510), w(1500, 3012), w(2900, 3014)];
        let s = classify(&one, &ran, LATE);
        assert_eq!((s.shared, s.alone, s.not_compared), (0, 1, 0));
        // Woke 80 µs before the end: within half the threshold, so shared; 150 µs before
        // it: the CPU ran it while `one` waited.
        let s = classify(&one, &[w(500, 2920)], LATE);
        assert_eq!((s.shared, s.alone, s.not_compared), (1, 0, 0));
        assert_eq!(class_of(one[0], &[w(500, 2850)], LATE), Class::Alone);
        // The other's wait began before this one was due and lasted to the same end:
        // shared. One that ended just after this one was due ran while it waited: alone.
        // One that ended before this one was due is not compared with it. One due within
        // `LATE` of the end is not compared either.
        let late = w(1000, 4000);
        assert_eq!(class_of(late, &[w(500, 4005)], LATE), Class::Shared);
        assert_eq!(class_of(late, &[w(500, 1005)], LATE), Class::Alone);
        assert_eq!(class_of(late, &[w(500, 510)], LATE), Class::NotCompared);
        assert_eq!(
            class_of(late, &[w(500, 510), w(1500, 4010)], LATE),
            Class::Shared
        );
        assert_eq!(class_of(late, &[w(3900, 3905)], LATE), Class::NotCompared);
        // Any overlapping wake-up that came well before the end makes it alone, even when
        // a later one waited until the end with it.
        assert_eq!(
            class_of(late, &[w(500, 1005), w(2000, 4004)], LATE),
            Class::Alone
        );
    }

    #[test]
    fn short_waits_between_the_others_grid_points_are_not_compared() {
        // 300 µs late with the other due only at 500: not compared; 10 µs late: not late.
        let s = classify(&[w(0, 300), w(1000, 1010)], &[w(500, 510)], LATE);
        assert_eq!((s.shared, s.alone, s.not_compared), (0, 0, 1));
        assert_eq!(classify(&[w(0, 3000)], &[], LATE).not_compared, 1);
    }

    #[test]
    fn every_wake_up_is_placed_whether_or_not_it_was_a_spike() {
        // Loops 0 and 2 were 1 µs late (no spike); loop 3 came 2.5 periods late, so the
        // grid point after it is skipped.
        let text = "       0:       0:       1\n       0:       1:      34\n\
                    \x20      0:       2:       1\n       0:       3:    2500\n\
                    \x20      0:       4:       0\n\n\
                    T: 0 Spike:      34: TS:  10001034\nT: 0 Spike:    2500: TS:  10005500\n";
        let wakes = cyclictest_wakes(text, 1_000_000).unwrap();
        assert_eq!(
            wakes,
            vec![
                w(10_000_000, 10_000_001),
                w(10_001_000, 10_001_034),
                w(10_002_000, 10_002_001),
                w(10_003_000, 10_005_500),
                w(10_006_000, 10_006_000),
            ]
        );
        // A spike whose latency is not its loop's, or one too few, is an error.
        let wrong = text.replace("Spike:      34", "Spike:      35");
        assert!(matches!(
            cyclictest_wakes(&wrong, 1_000_000),
            Err(ReadError::Mismatch { loop_: 1, .. })
        ));
        let short = text.replace("T: 0 Spike:    2500: TS:  10005500\n", "");
        assert!(matches!(
            cyclictest_wakes(&short, 1_000_000),
            Err(ReadError::Count { spikes: 1, late: 2 })
        ));
        assert_eq!(cyclictest_wakes("", 1_000_000), Err(ReadError::NoLatencies));
    }

    #[test]
    fn spikes_are_read_with_their_times() {
        let text = "# /dev/cpu_dma_latency set to 0us\n\
                    T: 0 (11012) P:80 I:1000 C:     20 Min:     14 Act:   19 Avg:   19 Max:  34\n\n\
                    T: 0 Spike:      34: TS:  31547001284\nT: 0 Spike:      15: TS:  31547002265\n\
                    spikes = 2\n";
        let s = cyclictest_spikes(text);
        assert_eq!(
            s,
            vec![
                w(31_547_001_250, 31_547_001_284),
                w(31_547_002_250, 31_547_002_265)
            ]
        );
    }
}
