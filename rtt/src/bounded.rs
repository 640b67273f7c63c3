//! A bounded multi-producer, multi-consumer queue that never waits for another thread:
//! D. Vyukov's bounded MPMC queue.
//!
//! Each slot carries a sequence number that says whose turn it is. A push claims the tail
//! position with a compare-and-swap when that slot's number says it is free, writes the
//! value and publishes it; a pop does the same at the head. Where a queue such as
//! crossbeam's `ArrayQueue` spins until a thread that claimed a slot finishes with it, this
//! one answers at once: a push that finds its slot not yet given back by the last pop
//! says "full", and a pop that finds its slot not yet written says "empty". A real-time
//! thread pushing a log record or an operation call therefore never waits for a
//! lower-priority thread preempted half-way through a pop (the logger thread, a control
//! client); it drops (and counts) or refuses instead. Compare-and-swap retries against other
//! pushers are the only loop: lock-free, never blocked by a thread that does not run.

use std::cell::UnsafeCell;
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicUsize, Ordering};

/// An index on its own cache line, so that pushers and poppers do not share one.
#[repr(align(64))]
struct Padded(AtomicUsize);

struct Slot<T> {
    /// `pos`: free for the push at `pos`; `pos + 1`: holds the value for the pop at `pos`.
    seq: AtomicUsize,
    value: UnsafeCell<MaybeUninit<T>>,
}

/// See the module's documentation.
pub struct Bounded<T> {
    slots: Box<[Slot<T>]>,
    head: Padded,
    tail: Padded,
}

// SAFETY: a value is written only by the push that claimed its slot, and read only by the
// pop that claimed it after the push published it (Release/Acquire on `seq`): each value
// moves from one thread to one other, so `T: Send` is enough.
#[allow(
    unsafe_code,
    reason = "values move through the slots between threads, ordered by each slot's sequence"
)]
unsafe impl<T: Send> Send for Bounded<T> {}
#[allow(
    unsafe_code,
    reason = "values move through the slots between threads, ordered by each slot's sequence"
)]
unsafe impl<T: Send> Sync for Bounded<T> {}

impl<T> Bounded<T> {
    /// A queue of `capacity` values (at least 1).
    pub fn new(capacity: usize) -> Self {
        let slots = (0..capacity.max(1))
            .map(|i| Slot {
                seq: AtomicUsize::new(i),
                value: UnsafeCell::new(MaybeUninit::uninit()),
            })
            .collect();
        Bounded {
            slots,
            head: Padded(AtomicUsize::new(0)),
            tail: Padded(AtomicUsize::new(0)),
        }
    }

    /// How many values it holds at most.
    pub fn capacity(&self) -> usize {
        self.slots.len()
    }

    /// About how many values it holds now.
    pub fn len(&self) -> usize {
        let tail = self.tail.0.load(Ordering::Relaxed);
        let head = self.head.0.load(Ordering::Relaxed);
        tail.wrapping_sub(head).min(self.capacity())
    }

    /// Whether it holds nothing now (about).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn slot(&self, pos: usize) -> &Slot<T> {
        &self.slots[pos % self.slots.len()]
    }

    /// Adds `value` at the tail; gives it back when the queue is full (or the slot's last
    /// pop has not finished: it never waits for it).
    #[allow(
        unsafe_code,
        reason = "values move through the slots between threads, ordered by each slot's sequence"
    )]
    pub fn push(&self, value: T) -> Result<(), T> {
        let mut pos = self.tail.0.load(Ordering::Relaxed);
        loop {
            let slot = self.slot(pos);
            let seq = slot.seq.load(Ordering::Acquire);
            // Wrapping difference, as a signed distance.
            let diff = seq.wrapping_sub(pos) as isize;
            if diff == 0 {
                match self.tail.0.compare_exchange_weak(
                    pos,
                    pos.wrapping_add(1),
                    Ordering::Relaxed,
                    Ordering::Relaxed,
                ) {
                    Ok(_) => {
                        // SAFETY: this push claimed `pos` while the slot was free: no other
                        // thread touches its value until `seq` says `pos + 1`.
                        unsafe { (*slot.value.get()).write(value) };
                        slot.seq.store(pos.wrapping_add(1), Ordering::Release);
                        return Ok(());
                    }
                    Err(now) => pos = now,
                }
            } else if diff < 0 {
                return Err(value);
            } else {
                pos = self.tail.0.load(Ordering::Relaxed);
            }
        }
    }

    /// Takes the value at the head; `None` when the queue is empty (or the head's push has
    /// not finished: it never waits for it).
    #[allow(
        unsafe_code,
        reason = "values move through the slots between threads, ordered by each slot's sequence"
    )]
    pub fn pop(&self) -> Option<T> {
        let mut pos = self.head.0.load(Ordering::Relaxed);
        loop {
            let slot = self.slot(pos);
            let seq = slot.seq.load(Ordering::Acquire);
            let diff = seq.wrapping_sub(pos.wrapping_add(1)) as isize;
            if diff == 0 {
                match self.head.0.compare_exchange_weak(
                    pos,
                    pos.wrapping_add(1),
                    Ordering::Relaxed,
                    Ordering::Relaxed,
                ) {
                    Ok(_) => {
                        // SAFETY: the push at `pos` wrote the value and published it (seq
                        // `pos + 1`, read with Acquire); this pop claimed it alone.
                        let value = unsafe { (*slot.value.get()).assume_init_read() };
                        slot.seq
                            .store(pos.wrapping_add(self.slots.len()), Ordering::Release);
                        return Some(value);
                    }
                    Err(now) => pos = now,
                }
            } else if diff < 0 {
                return None;
            } else {
                pos = self.head.0.load(Ordering::Relaxed);
            }
        }
    }
}

impl<T> Drop for Bounded<T> {
    fn drop(&mut self) {
        // What is still queued is dropped with the queue.
        while self.pop().is_some() {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::sync::atomic::AtomicU64;

    #[test]
    fn first_in_first_out_and_full_gives_the_value_back() {
        let q = Bounded::new(3);
        assert_eq!(q.pop(), None);
        for i in 0..3 {
            q.push(i).unwrap();
        }
        assert_eq!(q.push(9), Err(9));
        assert_eq!(q.len(), 3);
        assert_eq!(q.pop(), Some(0));
        q.push(3).unwrap();
        let got: Vec<i32> = std::iter::from_fn(|| q.pop()).collect();
        assert_eq!(got, [1, 2, 3]);
        assert!(q.is_empty());
        // Around the ring many times.
        for i in 0..1000 {
            q.push(i).unwrap();
            assert_eq!(q.pop(), Some(i));
        }
    }

    #[test]
    fn what_is_left_is_dropped_with_the_queue() {
        let token = Arc::new(());
        let q = Bounded::new(4);
        q.push(token.clone()).unwrap();
        q.push(token.clone()).unwrap();
        drop(q.pop());
        assert_eq!(Arc::strong_count(&token), 2);
        drop(q);
        assert_eq!(Arc::strong_count(&token), 1);
    }

    #[test]
    fn many_pushers_and_poppers_lose_and_repeat_nothing() {
        const PUSHERS: u64 = 4;
        const EACH: u64 = 50_000;
        let q = Arc::new(Bounded::new(16));
        let sum = Arc::new(AtomicU64::new(0));
        let count = Arc::new(AtomicU64::new(0));
        std::thread::scope(|s| {
            for p in 0..PUSHERS {
                let q = q.clone();
                s.spawn(move || {
                    for i in 0..EACH {
                        let mut v = p * EACH + i + 1;
                        while let Err(back) = q.push(v) {
                            v = back;
                            std::thread::yield_now();
                        }
                    }
                });
            }
            for _ in 0..2 {
                let (q, sum, count) = (q.clone(), sum.clone(), count.clone());
                s.spawn(move || {
                    while count.load(Ordering::Relaxed) < PUSHERS * EACH {
                        match q.pop() {
                            Some(v) => {
                                sum.fetch_add(v, Ordering::Relaxed);
                                count.fetch_add(1, Ordering::Relaxed);
                            }
                            None => std::thread::yield_now(),
                        }
                    }
                });
            }
        });
        let n = PUSHERS * EACH;
        assert_eq!(count.load(Ordering::Relaxed), n);
        assert_eq!(sum.load(Ordering::Relaxed), n * (n + 1) / 2);
    }
}
