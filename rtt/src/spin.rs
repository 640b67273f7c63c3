//! Waiting by spinning for a bounded time before parking, as crossbeam's channels do: a
//! thread that is handed work (a trigger, an OwnThread call's result) within the bound
//! sees it within a few nanoseconds instead of a scheduler wake-up (microseconds, more in a
//! virtual machine), and a thread that is not spends at most the bound busy. After 2 µs of
//! pure spinning the spin yields between looks: Linux tends to wake a thread on its
//! waker's CPU, and a waker that spun without yielding would keep the thread it woke (the
//! engine that has the call, the caller that has the result) from running. A SCHED_FIFO
//! thread's spin is pure to its bound: its yield would let no lower-priority thread run,
//! and a real-time thread's steady state makes no `sched_yield` (a thread of the same
//! priority on the same CPU waits out the bound instead).

use std::cell::Cell;
use std::time::{Duration, Instant};

thread_local! {
    /// Set on a thread that got SCHED_FIFO: its spins never yield, so that its steady state
    /// makes no `sched_yield`. A SCHED_FIFO thread's yield lets only threads of its own
    /// priority on its CPU run, never a lower one; the cost of not yielding falls on a
    /// thread of the same priority pinned to the same CPU, which waits at most the spin's
    /// bound (`spin_us`) before the spinning thread parks.
    static REALTIME: Cell<bool> = const { Cell::new(false) };
    /// Set when this thread has just unparked another: the scheduler tends to wake that
    /// thread on this one's CPU, so this thread's next wait parks at once rather than spin
    /// and keep it from running.
    static WOKE_ANOTHER: Cell<bool> = const { Cell::new(false) };
}

/// Notes that this thread runs SCHED_FIFO: its spins stay pure (no `sched_yield`).
pub(crate) fn note_realtime() {
    REALTIME.with(|r| r.set(true));
}

/// Notes that this thread unparked another thread (see [`take_woke_another`]).
pub(crate) fn note_woke_another() {
    WOKE_ANOTHER.with(|w| w.set(true));
}

/// True (once) when this thread unparked another since the last call.
pub(crate) fn take_woke_another() -> bool {
    WOKE_ANOTHER.with(|w| w.replace(false))
}

/// Checks between two looks at the clock: a look costs about as much as 16 spin-loop
/// hints, so the bound is kept to within a few hundred nanoseconds.
const CHECKS_PER_CLOCK: u32 = 16;

/// How long a spin is pure before it yields between looks.
const YIELD_AFTER: Duration = Duration::from_micros(2);

/// Spins until `done` holds or `budget` has passed; true when it holds. A zero budget
/// looks once.
pub(crate) fn spin_until(budget: Duration, mut done: impl FnMut() -> bool) -> bool {
    if done() {
        return true;
    }
    if budget.is_zero() {
        return false;
    }
    let start = Instant::now();
    let may_yield = !REALTIME.with(Cell::get);
    loop {
        for _ in 0..CHECKS_PER_CLOCK {
            std::hint::spin_loop();
            if done() {
                return true;
            }
        }
        let spent = start.elapsed();
        if spent >= budget {
            return done();
        }
        if may_yield && spent >= YIELD_AFTER {
            // Past a short pure spin, give the CPU to whatever else is runnable here (a
            // thread this one woke may have been put on this CPU) between looks.
            std::thread::yield_now();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bound_holds_and_a_condition_ends_it() {
        let t0 = Instant::now();
        assert!(!spin_until(Duration::from_micros(200), || false));
        let spent = t0.elapsed();
        assert!(spent >= Duration::from_micros(200), "{spent:?}");
        let mut n = 0;
        assert!(spin_until(Duration::from_secs(10), || {
            n += 1;
            n == 100
        }));
        assert!(!spin_until(Duration::ZERO, || false));
    }
}
