//! Operations: named, documented, typed functions a component offers to others.
//!
//! An operation runs either in the caller's thread ([`ExecutionThread::ClientThread`]: no
//! queue, no wait, no allocation) or in the component's own thread
//! ([`ExecutionThread::OwnThread`]: queued to the component's engine, run before its next
//! update with `&mut` access to the component). Callers hold an [`OperationCaller`]: `call()`
//! blocks for the result, `send()` returns a [`SendHandle`] to `collect()` later. A call to a
//! component that is not running, or that is gone, is an error, not a hang or a crash.
//!
//! Arguments travel as a tuple; every operation can also be called with dynamically typed
//! (JSON) arguments, which is how the control socket calls it.

use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::any::Any;
use std::sync::{Arc, Weak};
use std::time::Duration;

mod slot;
pub use slot::QUEUE_CAPACITY;
pub(crate) use slot::Queued;
use slot::{CallSlot, Outcome};

/// Which thread runs an operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExecutionThread {
    /// The caller's thread, at once.
    ClientThread,
    /// The component's own thread, before its next update.
    OwnThread,
}

/// Why a call did not produce a result.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CallError {
    /// The component's engine is not running, so an OwnThread operation cannot run.
    #[error(
        "operation {operation:?} runs in component {component:?}'s thread, which is not running (state {state})"
    )]
    NotRunning {
        /// The operation.
        operation: String,
        /// The component.
        component: String,
        /// Its lifecycle state.
        state: String,
    },
    /// The component offering the operation is gone.
    #[error("operation {operation:?}: the component offering it is gone")]
    Vanished {
        /// The operation.
        operation: String,
    },
    /// The operation panicked; the component keeps running.
    #[error("operation {operation:?} panicked: {message}")]
    Panicked {
        /// The operation.
        operation: String,
        /// The panic message.
        message: String,
    },
    /// The component stopped before running the queued call.
    #[error("operation {operation:?} was cancelled: its component stopped before running it")]
    Cancelled {
        /// The operation.
        operation: String,
    },
    /// An OwnThread operation called from its own component's update (it would wait for
    /// itself).
    #[error(
        "operation {operation:?} was called from its own component's thread; call the function directly"
    )]
    Reentrant {
        /// The operation.
        operation: String,
    },
    /// Dynamically typed arguments that do not fit.
    #[error("operation {operation:?} takes {expected}: {detail}")]
    WrongArguments {
        /// The operation.
        operation: String,
        /// The argument types.
        expected: String,
        /// What was wrong.
        detail: String,
    },
    /// A required operation whose binding is not ready: unbound, or its provider not
    /// Running.
    #[error(
        "required operation {operation:?} is not ready: not bound, or its provider is not running"
    )]
    NotReady {
        /// The operation.
        operation: Arc<str>,
    },
    /// `collect` after the result was already taken.
    #[error("the result was already collected")]
    AlreadyCollected,
    /// The component's queue of OwnThread calls is full: the call was not queued.
    #[error(
        "operation {operation:?} was refused: component {component:?} has {capacity} calls queued already"
    )]
    QueueFull {
        /// The operation.
        operation: String,
        /// The component.
        component: String,
        /// The queue's capacity ([`QUEUE_CAPACITY`]).
        capacity: usize,
    },
    /// A call to an operation in another process (a service of another gateway) that
    /// brought no result of the type required.
    #[error("operation {operation:?} of the remote provider: {message}")]
    Remote {
        /// The operation (`service.member`).
        operation: String,
        /// Why: no answer, the other side's error, or an answer of another type.
        message: String,
    },
}

/// One argument, as documented.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct ArgInfo {
    /// Name.
    pub name: String,
    /// What it means.
    pub doc: String,
    /// Type, as the control protocol names it ([`crate::typename`]).
    pub type_name: String,
}

/// An operation, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct OperationInfo {
    /// Name.
    pub name: String,
    /// What it does.
    pub doc: String,
    /// Arguments, in order.
    pub args: Vec<ArgInfo>,
    /// Type of the result, as the control protocol names it ([`crate::typename`]): a
    /// `Result`'s value (its error is the call's), empty when the call answers nothing.
    pub result: String,
    /// Which thread runs it.
    pub thread: ExecutionThread,
}

/// Argument tuples: `()`, `(A,)`, `(A, B)`, … up to five.
pub trait Args: DeserializeOwned + Send + 'static {
    /// Number of arguments.
    const ARITY: usize;
    /// Rust type names of the arguments.
    fn type_names() -> Vec<&'static str>;
}

impl Args for () {
    const ARITY: usize = 0;
    fn type_names() -> Vec<&'static str> {
        Vec::new()
    }
}

macro_rules! args_tuple {
    ($n:expr; $($t:ident),+) => {
        impl<$($t: DeserializeOwned + Send + 'static),+> Args for ($($t,)+) {
            const ARITY: usize = $n;
            fn type_names() -> Vec<&'static str> {
                vec![$(std::any::type_name::<$t>()),+]
            }
        }
    };
}
args_tuple!(1; A);
args_tuple!(2; A, B);
args_tuple!(3; A, B, C);
args_tuple!(4; A, B, C, D);
args_tuple!(5; A, B, C, D, E);

/// What queues OwnThread calls: the component's engine.
pub(crate) trait Engine: Send + Sync {
    /// Queues `call` and wakes the engine, or says why not and gives the call back; `Ok`
    /// carries how long the caller may spin for the result before it parks (the engine's
    /// thread option `spin_us` for a non-periodic engine, which answers at once; zero for
    /// the others). Takes no lock and allocates nothing.
    fn submit(&self, operation: &str, call: Queued) -> Result<Duration, (CallError, Queued)>;
    /// Counts a call slot made on the heap because every pooled one was in use.
    fn note_slot_allocated(&self);
}

/// The pending or finished result of [`OperationCaller::send`].
pub struct SendHandle<R> {
    state: HandleState<R>,
}

enum HandleState<R> {
    Ready(Result<R, CallError>),
    /// Queued: the result to come, and how long `collect` spins for it before parking.
    Pending(Arc<dyn Outcome<R>>, Duration),
    Taken,
}

impl<R> Drop for SendHandle<R> {
    fn drop(&mut self) {
        // A call sent and never collected: its slot is freed once the result comes.
        if let HandleState::Pending(slot, _) = &self.state {
            slot.abandon();
        }
    }
}

impl<R> SendHandle<R> {
    /// A handle whose result is known already.
    pub(crate) fn ready(result: Result<R, CallError>) -> Self {
        SendHandle {
            state: HandleState::Ready(result),
        }
    }

    /// Waits for the result and takes it.
    pub fn collect(mut self) -> Result<R, CallError> {
        match std::mem::replace(&mut self.state, HandleState::Taken) {
            HandleState::Ready(r) => r,
            HandleState::Taken => Err(CallError::AlreadyCollected),
            HandleState::Pending(slot, spin) => {
                // A result within the spin is taken at once; after it, the caller parks
                // until the engine unparks it (the waiter is set before `done` is looked
                // at again, and `complete` sets `done` before it looks at the waiter).
                if !crate::spin::spin_until(spin, || slot.is_done())
                    && slot.park_as(std::thread::current())
                {
                    while !slot.is_done() {
                        // Bounded park: a wake-up aimed at another thread cannot strand us.
                        std::thread::park_timeout(Duration::from_millis(1));
                    }
                }
                slot.take()
            }
        }
    }

    /// The result if the call has finished (`None` if not yet); a second call after a
    /// result gives [`CallError::AlreadyCollected`].
    pub fn collect_if_done(&mut self) -> Option<Result<R, CallError>> {
        match &self.state {
            HandleState::Pending(slot, _) if !slot.is_done() => return None,
            _ => {}
        }
        Some(
            match std::mem::replace(&mut self.state, HandleState::Taken) {
                HandleState::Ready(r) => r,
                HandleState::Taken => Err(CallError::AlreadyCollected),
                HandleState::Pending(slot, _) => slot.take(),
            },
        )
    }
}

pub(crate) trait Invoke<A, R>: Send + Sync {
    fn call(&self, args: A) -> Result<R, CallError>;
    fn send(&self, args: A) -> SendHandle<R>;
}

fn panic_message(p: &(dyn Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".to_string())
}

pub(crate) struct ClientOp<F> {
    pub(crate) name: Arc<str>,
    pub(crate) f: F,
}

impl<A, R, F> Invoke<A, R> for ClientOp<F>
where
    F: Fn(A) -> R + Send + Sync,
{
    fn call(&self, args: A) -> Result<R, CallError> {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (self.f)(args))).map_err(|p| {
            CallError::Panicked {
                operation: self.name.to_string(),
                message: panic_message(p.as_ref()),
            }
        })
    }

    fn send(&self, args: A) -> SendHandle<R> {
        SendHandle {
            state: HandleState::Ready(self.call(args)),
        }
    }
}

pub(crate) struct OwnOp<C, A, R, F> {
    name: Arc<str>,
    f: Arc<F>,
    engine: Weak<dyn Engine>,
    /// Call slots made with the operation ([`slot::POOL`]).
    pool: Vec<Arc<CallSlot<C, A, R, F>>>,
}

impl<C, A, R, F> OwnOp<C, A, R, F>
where
    C: 'static,
    A: Send + 'static,
    R: Send + 'static,
    F: Fn(&mut C, A) -> R + Send + Sync + 'static,
{
    /// Operation `name` running `f` on `engine`'s component, with its slots.
    pub(crate) fn new(name: &str, f: F, engine: Weak<dyn Engine>) -> Self {
        let name: Arc<str> = Arc::from(name);
        let f = Arc::new(f);
        let pool = (0..slot::POOL)
            .map(|_| Arc::new(CallSlot::new(f.clone(), name.clone())))
            .collect();
        OwnOp {
            name,
            f,
            engine,
            pool,
        }
    }

    /// A slot claimed for `args`: a free one of the pool, or a new one (counted).
    fn claim(&self, engine: &dyn Engine, mut args: A) -> Arc<CallSlot<C, A, R, F>> {
        for slot in &self.pool {
            match slot.claim(args) {
                Ok(()) => return slot.clone(),
                Err(back) => args = back,
            }
        }
        engine.note_slot_allocated();
        let slot = Arc::new(CallSlot::new(self.f.clone(), self.name.clone()));
        // A new slot is free: the claim cannot fail.
        let _ = slot.claim(args);
        slot
    }
}

impl<C, A, R, F> Invoke<A, R> for OwnOp<C, A, R, F>
where
    C: 'static,
    A: Send + 'static,
    R: Send + 'static,
    F: Fn(&mut C, A) -> R + Send + Sync + 'static,
{
    fn call(&self, args: A) -> Result<R, CallError> {
        self.send(args).collect()
    }

    fn send(&self, args: A) -> SendHandle<R> {
        let Some(engine) = self.engine.upgrade() else {
            return SendHandle::ready(Err(CallError::Vanished {
                operation: self.name.to_string(),
            }));
        };
        let slot = self.claim(engine.as_ref(), args);
        match engine.submit(&self.name, slot::queued(slot.clone())) {
            Ok(spin) => SendHandle {
                state: HandleState::Pending(slot, spin),
            },
            Err((e, call)) => {
                call.refused();
                SendHandle::ready(Err(e))
            }
        }
    }
}

/// A typed handle to call an operation.
pub struct OperationCaller<A, R> {
    pub(crate) name: Arc<str>,
    pub(crate) inner: Arc<dyn Invoke<A, R>>,
}

impl<A, R> Clone for OperationCaller<A, R> {
    fn clone(&self) -> Self {
        OperationCaller {
            name: self.name.clone(),
            inner: self.inner.clone(),
        }
    }
}

impl<A, R> OperationCaller<A, R> {
    /// Runs the operation and waits for its result. A ClientThread operation runs here and
    /// now, allocation-free; an OwnThread one is queued to its component and waited for.
    pub fn call(&self, args: A) -> Result<R, CallError> {
        self.inner.call(args)
    }

    /// Starts the operation and returns at once with a handle to collect the result.
    pub fn send(&self, args: A) -> SendHandle<R> {
        self.inner.send(args)
    }

    /// The operation's name.
    pub fn name(&self) -> &str {
        &self.name
    }
}

/// An operation as the dynamic interface sees it.
pub(crate) trait DynOperation: Send + Sync {
    fn info(&self) -> &OperationInfo;
    /// `fn(A, B) -> R` in Rust's names, for a Rust caller that asked for other types.
    fn rust_signature(&self) -> String;
    fn call_value(&self, args: Vec<Value>) -> Result<Value, CallError>;
    fn send_value(&self, args: Vec<Value>) -> Result<ValueHandle, CallError>;
    fn as_any(&self) -> &dyn Any;
}

/// The pending or finished result of a send through the dynamic layer
/// ([`TaskContext::send_value`](crate::TaskContext::send_value)), as a value.
pub struct ValueHandle {
    poll: Box<dyn FnMut() -> Option<Result<Value, CallError>> + Send>,
}

impl ValueHandle {
    /// The result if the call has finished (`None` if not yet); after a result,
    /// [`CallError::AlreadyCollected`].
    pub fn collect_if_done(&mut self) -> Option<Result<Value, CallError>> {
        (self.poll)()
    }
}

impl std::fmt::Debug for ValueHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ValueHandle")
    }
}

/// `r` as a value, or why it is none.
fn result_value<R: Serialize>(operation: &str, r: &R) -> Result<Value, CallError> {
    serde_json::to_value(r).map_err(|e| CallError::WrongArguments {
        operation: operation.to_string(),
        expected: "a result that serialises".into(),
        detail: e.to_string(),
    })
}

pub(crate) struct OperationEntry<A, R> {
    pub(crate) info: OperationInfo,
    pub(crate) caller: OperationCaller<A, R>,
}

impl<A: Args, R: Serialize + 'static> OperationEntry<A, R> {
    /// `args` as the operation's argument tuple, or what does not fit.
    fn arguments(&self, args: Vec<Value>) -> Result<A, CallError> {
        let wrong = |detail: String| {
            let types: Vec<&str> = self
                .info
                .args
                .iter()
                .map(|a| a.type_name.as_str())
                .collect();
            CallError::WrongArguments {
                operation: self.info.name.clone(),
                expected: format!("({})", types.join(", ")),
                detail,
            }
        };
        if args.len() != A::ARITY {
            return Err(wrong(format!(
                "{} arguments given, {} expected",
                args.len(),
                A::ARITY
            )));
        }
        let value = if A::ARITY == 0 {
            Value::Null
        } else {
            Value::Array(args)
        };
        serde_json::from_value(value).map_err(|e| wrong(e.to_string()))
    }
}

impl<A: Args, R: Serialize + Send + 'static> DynOperation for OperationEntry<A, R> {
    fn info(&self) -> &OperationInfo {
        &self.info
    }

    fn rust_signature(&self) -> String {
        format!(
            "fn({}) -> {}",
            A::type_names().join(", "),
            std::any::type_name::<R>()
        )
    }

    fn call_value(&self, args: Vec<Value>) -> Result<Value, CallError> {
        let r = self.caller.call(self.arguments(args)?)?;
        result_value(&self.info.name, &r)
    }

    fn send_value(&self, args: Vec<Value>) -> Result<ValueHandle, CallError> {
        let mut handle = self.caller.send(self.arguments(args)?);
        let name = self.info.name.clone();
        Ok(ValueHandle {
            poll: Box::new(move || {
                handle
                    .collect_if_done()
                    .map(|r| r.and_then(|r| result_value(&name, &r)))
            }),
        })
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
