//! The jitter bench's third piece of a round: hwgw's periodic activity and cyclictest in
//! the same seconds, pinned to the same CPU, so that a stall of that CPU — the host taking
//! the vCPU, an interrupt storm, the guest kernel — delays both, and a late wake-up of one
//! can be set beside what the other did at that moment.
//!
//! The two run half a period apart: the probe starts first, its grid is read from its first
//! step, and cyclictest is started with `--secaligned` at the grid point half a period on
//! (its wake-ups fall at whole seconds plus that offset). Neither's step (tens of µs here)
//! reaches into the other's wake-up. cyclictest's `--spike=1` gives the time on the
//! monotonic clock (µs) of each wake-up over 1 µs late, and `-v` every latency, so both
//! programs' wake-ups are placed to the µs ([`testkit::stalls::cyclictest_wakes`]). The
//! figures count the probe's steps due while cyclictest ran; the steal printed covers the
//! whole piece, start-up included.
//!
//! Each program's wake-ups more than [`LATE_US`] late (the lateness that makes a 1.2×
//! period after an on-time one) are set against the other's waits that overlap them
//! ([`testkit::stalls::classify`]): **shared** when those lasted until about the same end —
//! the CPU ran neither, the machine's stall; **alone** when one ended well before — the CPU
//! ran the other program while this one waited, this program's own delay; **not
//! compared** when none overlapped.

use crate::report::Settings;
use crate::{Figures, LATE_US, PERIOD_US, figures, start_probe};
use std::sync::atomic::Ordering;
use testkit::stalls::{Class, Seen, Wake, class_of, classify, cyclictest_wakes};

/// One piece run together: both programs' figures over the same seconds, and their late
/// wake-ups classified.
pub struct Together {
    pub ours: Figures,
    pub theirs: Figures,
    pub ours_seen: Seen,
    pub theirs_seen: Seen,
    /// Each program's most late wake-up set against the other's, when it was more than
    /// [`LATE_US`] late.
    pub worst: (Option<Class>, Option<Class>),
    /// Where in each period the two grids fall, µs.
    pub phases: (u64, u64),
    pub cpu: usize,
}

/// Runs the probe and cyclictest together on the settings' CPU for as many of cyclictest's
/// wake-ups as the settings ask.
pub fn run(set: &Settings) -> Result<Together, String> {
    let (loops, fifo, priority, cpu) = (set.loops, set.fifo, set.priority, set.cpu);
    // Installed first: an installation must not eat the probe's margin.
    testkit::peers::require(&testkit::peers::CYCLICTEST).map_err(|e| e.to_string())?;
    // Room for the probe's steps while cyclictest starts (locking its memory, waiting for
    // the next whole second) and runs.
    let margin = 10_000_000 / PERIOD_US;
    let steal = testkit::bench::steal_ms();
    let run = start_probe(loops + margin, fifo, priority, vec![cpu]);
    let ours_phase = run.trace.due_ns[0].load(Ordering::Relaxed) / 1000 % PERIOD_US;
    let theirs_phase = (ours_phase + PERIOD_US / 2) % PERIOD_US;
    let prio = if fifo { priority } else { 0 };
    let (pin, aligned, nodes) = (
        format!("-a{cpu}"),
        format!("--secaligned={theirs_phase}"),
        format!("--spike-nodes={loops}"),
    );
    let main = set.cyclictest_main();
    let mut extra = vec!["-v", &pin, &aligned, "--spike=1", &nodes];
    extra.extend(main.as_deref());
    let out = testkit::bench::cyclictest(prio, PERIOD_US, loops, &extra);
    let stopped = run.task.stop();
    let (text, _) = out?;
    stopped.map_err(|e| e.to_string())?;
    let steal = testkit::bench::steal_ms().saturating_sub(steal);
    let theirs = cyclictest_wakes(&text, PERIOD_US * 1000).map_err(|e| e.to_string())?;
    if theirs.len() as u64 != loops {
        return Err(format!(
            "cyclictest's {} wake-ups placed in time, of {loops}",
            theirs.len()
        ));
    }
    let (from, to) = (theirs[0].due, theirs[theirs.len() - 1].woke);
    let steps = run.trace.steps();
    if steps.last().is_none_or(|s| s.1 < to) {
        return Err("the probe's trace ended before cyclictest's run did".to_string());
    }
    // All of the probe's steps, to set cyclictest's first wake-ups against; those due
    // while cyclictest ran, for the figures.
    let all: Vec<Wake> = steps
        .iter()
        .map(|s| Wake {
            due: s.2,
            woke: s.1,
        })
        .collect();
    let inside = |w: &Wake| w.due >= from && w.due <= to;
    let ours: Vec<Wake> = all.iter().copied().filter(inside).collect();
    let late_us = |w: &[Wake]| -> Vec<u64> { w.iter().map(|w| (w.woke - w.due) / 1000).collect() };
    let intervals = |w: &[Wake]| -> Vec<u64> {
        w.windows(2)
            .map(|p| (p[1].woke - p[0].woke) / 1000)
            .collect()
    };
    let late_ns = LATE_US * 1000;
    Ok(Together {
        ours: figures(
            &late_us(&ours),
            intervals(&ours).into_iter(),
            steal,
            Default::default(),
        ),
        theirs: figures(
            &late_us(&theirs),
            intervals(&theirs).into_iter(),
            steal,
            Default::default(),
        ),
        worst: (
            most_late(&ours, late_ns).map(|w| class_of(w, &theirs, late_ns)),
            most_late(&theirs, late_ns).map(|w| class_of(w, &all, late_ns)),
        ),
        ours_seen: classify(&ours, &theirs, late_ns),
        theirs_seen: classify(&theirs, &all, late_ns),
        phases: (ours_phase, theirs_phase),
        cpu,
    })
}

/// The most late of some wake-ups, when it was more than `late_ns` late.
fn most_late(w: &[Wake], late_ns: u64) -> Option<Wake> {
    w.iter()
        .copied()
        .max_by_key(|w| w.woke.saturating_sub(w.due))
        .filter(|w| w.woke.saturating_sub(w.due) > late_ns)
}
