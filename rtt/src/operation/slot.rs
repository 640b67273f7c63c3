//! The call slots of OwnThread operations: a `send` that allocates nothing and takes no
//! lock.
//!
//! Each OwnThread operation keeps a small pool of [`CallSlot`]s, made when the component is
//! built. A `send` claims a free slot with one compare-and-swap, moves its arguments in, and
//! queues a [`Queued`] (a counted reference to the slot, no allocation) on the component's
//! bounded lock-free queue. The engine thread runs the call, writes the result into the slot
//! and publishes it with one atomic store; it wakes the caller only if the caller parked.
//! The caller takes the result and the slot is free again. Neither side ever waits on a lock
//! the other (or any third thread) can hold, so a high-priority caller is never blocked
//! behind a low-priority engine, nor the engine behind a caller.
//!
//! When every slot of an operation is in use (more calls outstanding at once than the
//! pool holds), `send` makes one more slot on the heap and counts it in the component's
//! counters (`call_slots_allocated`): correct, but no longer allocation-free.
//!
//! The slot's state word hands its three cells from one thread to the other:
//!
//! | state | arguments | result | waiter |
//! |---|---|---|---|
//! | `FREE` | nobody | nobody | nobody |
//! | `QUEUED` | caller writes, then the engine takes (the queue orders the two) | engine writes | caller writes |
//! | `PARKED` | engine | engine writes | engine reads |
//! | `DONE` | nobody | caller takes | nobody |
//! | `ABANDONED` | engine | engine drops | nobody |

use super::{CallError, panic_message};
use std::any::Any;
use std::cell::UnsafeCell;
use std::marker::PhantomData;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::thread::Thread;

/// Slots each OwnThread operation keeps: calls to it outstanding at once without an
/// allocation.
pub(crate) const POOL: usize = 4;

/// OwnThread calls a component's queue holds before it refuses more
/// ([`CallError::QueueFull`]).
pub const QUEUE_CAPACITY: usize = 256;

const FREE: u8 = 0;
const QUEUED: u8 = 1;
const PARKED: u8 = 2;
const DONE: u8 = 3;
const ABANDONED: u8 = 4;

/// What the engine does with a queued call.
pub(crate) trait Call: Send + Sync {
    /// Runs the call on the component (`&mut dyn Any`) and publishes its result.
    fn run(&self, component: &mut dyn Any);
    /// Publishes `Cancelled`: the call will never run.
    fn cancel(&self);
    /// Lets go of a call that was never queued: the slot is free again.
    fn release(&self);
}

/// The caller's side of a slot.
pub(crate) trait Outcome<R>: Send + Sync {
    /// The result is there.
    fn is_done(&self) -> bool;
    /// Notes `me` as the thread to wake; false when the result is there already.
    fn park_as(&self, me: Thread) -> bool;
    /// The result, once [`is_done`](Self::is_done); the slot is free again.
    fn take(&self) -> Result<R, CallError>;
    /// The handle is dropped unread: the result is dropped when it comes.
    fn abandon(&self);
}

/// A call on a component's queue. Dropped without running (the queue drained at a stop,
/// or dropped with its component), its caller gets [`CallError::Cancelled`].
pub(crate) struct Queued(Option<Arc<dyn Call>>);

impl Queued {
    /// Runs the call on `component`.
    pub(crate) fn run(mut self, component: &mut dyn Any) {
        if let Some(call) = self.0.take() {
            call.run(component);
        }
    }

    /// A call the queue did not take: its slot is freed, and its caller is answered by
    /// whoever refused it.
    pub(crate) fn refused(mut self) {
        if let Some(call) = self.0.take() {
            call.release();
        }
    }
}

impl Drop for Queued {
    fn drop(&mut self) {
        if let Some(call) = self.0.take() {
            call.cancel();
        }
    }
}

/// One call of operation `F` on component `C`: its arguments, its result, and who waits.
pub(crate) struct CallSlot<C, A, R, F> {
    state: AtomicU8,
    args: UnsafeCell<Option<A>>,
    result: UnsafeCell<Option<Result<R, CallError>>>,
    waiter: UnsafeCell<Option<Thread>>,
    f: Arc<F>,
    name: Arc<str>,
    _component: PhantomData<fn(&mut C)>,
}

// SAFETY: the cells are only touched by the thread the state word gives them to (the
// table in the module's documentation), and every hand-over is a Release store or
// exchange read by an Acquire load; what crosses threads (A, R, Thread) is Send.
#[allow(
    unsafe_code,
    reason = "the state word hands the cells between caller and engine; see the table above"
)]
unsafe impl<C, A: Send, R: Send, F: Send + Sync> Sync for CallSlot<C, A, R, F> {}

#[allow(
    unsafe_code,
    reason = "the state word hands the cells between caller and engine; see the table above"
)]
impl<C, A, R, F> CallSlot<C, A, R, F>
where
    C: 'static,
    A: Send + 'static,
    R: Send + 'static,
    F: Fn(&mut C, A) -> R + Send + Sync + 'static,
{
    /// A free slot.
    pub(crate) fn new(f: Arc<F>, name: Arc<str>) -> Self {
        CallSlot {
            state: AtomicU8::new(FREE),
            args: UnsafeCell::new(None),
            result: UnsafeCell::new(None),
            waiter: UnsafeCell::new(None),
            f,
            name,
            _component: PhantomData,
        }
    }

    /// Claims the slot for a call with `args`; gives the arguments back when it is in use.
    pub(crate) fn claim(&self, args: A) -> Result<(), A> {
        if self
            .state
            .compare_exchange(FREE, QUEUED, Ordering::Acquire, Ordering::Relaxed)
            .is_err()
        {
            return Err(args);
        }
        // SAFETY: QUEUED and not yet on the queue: the arguments are the caller's.
        unsafe { *self.args.get() = Some(args) };
        Ok(())
    }

    /// Publishes `r`, waking a parked caller (engine side).
    fn finish(&self, r: Result<R, CallError>) {
        // SAFETY: QUEUED, PARKED or ABANDONED: the result is the engine's until DONE.
        unsafe { *self.result.get() = Some(r) };
        let mut state = self.state.load(Ordering::Acquire);
        loop {
            match state {
                PARKED => {
                    // SAFETY: the caller wrote the waiter before PARKED and leaves it
                    // until DONE; a clone is a count, not an allocation.
                    let waiter = unsafe { (*self.waiter.get()).clone() };
                    self.state.store(DONE, Ordering::Release);
                    if let Some(t) = waiter {
                        t.unpark();
                        crate::spin::note_woke_another();
                    }
                    return;
                }
                QUEUED => {
                    match self.state.compare_exchange(
                        QUEUED,
                        DONE,
                        Ordering::AcqRel,
                        Ordering::Acquire,
                    ) {
                        Ok(_) => return,
                        Err(now) => state = now,
                    }
                }
                ABANDONED => {
                    // Nobody will take it.
                    // SAFETY: ABANDONED: the result is the engine's.
                    drop(unsafe { (*self.result.get()).take() });
                    self.state.store(FREE, Ordering::Release);
                    return;
                }
                // FREE and DONE do not happen while a call is queued: nothing to publish.
                _ => return,
            }
        }
    }
}

#[allow(
    unsafe_code,
    reason = "the state word hands the cells between caller and engine; see the table above"
)]
impl<C, A, R, F> Call for CallSlot<C, A, R, F>
where
    C: 'static,
    A: Send + 'static,
    R: Send + 'static,
    F: Fn(&mut C, A) -> R + Send + Sync + 'static,
{
    fn run(&self, component: &mut dyn Any) {
        // SAFETY: popped from the queue: the arguments are the engine's now.
        let args = unsafe { (*self.args.get()).take() };
        let result = match (args, component.downcast_mut::<C>()) {
            (Some(args), Some(c)) => {
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (self.f)(c, args)))
                    .map_err(|p| CallError::Panicked {
                        operation: self.name.to_string(),
                        message: panic_message(p.as_ref()),
                    })
            }
            (None, _) => Err(CallError::AlreadyCollected),
            (Some(_), None) => Err(CallError::Vanished {
                operation: self.name.to_string(),
            }),
        };
        self.finish(result);
    }

    fn cancel(&self) {
        // SAFETY: off the queue and never run: the arguments are this thread's.
        drop(unsafe { (*self.args.get()).take() });
        self.finish(Err(CallError::Cancelled {
            operation: self.name.to_string(),
        }));
    }

    fn release(&self) {
        // SAFETY: refused by the queue: the arguments never left the caller.
        drop(unsafe { (*self.args.get()).take() });
        self.state.store(FREE, Ordering::Release);
    }
}

#[allow(
    unsafe_code,
    reason = "the state word hands the cells between caller and engine; see the table above"
)]
impl<C, A, R, F> Outcome<R> for CallSlot<C, A, R, F>
where
    C: 'static,
    A: Send + 'static,
    R: Send + 'static,
    F: Fn(&mut C, A) -> R + Send + Sync + 'static,
{
    fn is_done(&self) -> bool {
        self.state.load(Ordering::Acquire) == DONE
    }

    fn park_as(&self, me: Thread) -> bool {
        // SAFETY: QUEUED: the waiter is the caller's until it publishes PARKED.
        unsafe { *self.waiter.get() = Some(me) };
        self.state
            .compare_exchange(QUEUED, PARKED, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
    }

    fn take(&self) -> Result<R, CallError> {
        if !self.is_done() {
            return Err(CallError::AlreadyCollected);
        }
        // SAFETY: DONE: the result is the caller's.
        let r = unsafe { (*self.result.get()).take() };
        self.state.store(FREE, Ordering::Release);
        r.unwrap_or(Err(CallError::AlreadyCollected))
    }

    fn abandon(&self) {
        if self
            .state
            .compare_exchange(QUEUED, ABANDONED, Ordering::AcqRel, Ordering::Acquire)
            .is_err()
        {
            // Done already: drop the result now.
            let _ = self.take();
        }
    }
}

/// `slot` queued as a call.
pub(crate) fn queued<S: Call + 'static>(slot: Arc<S>) -> Queued {
    Queued(Some(slot))
}
