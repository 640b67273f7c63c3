//! A card's bus side, handed over by value: what a driver's build returns beside its
//! [`Card`](crate::Card), and the gateway runs once on the card's thread settings.
//!
//! A [`BusSide`] is a run-once value: [`BusSide::add_to`] takes it by value, so a bus side
//! cannot be added twice, and a driver keeps no cell to take it from. Whatever the bus
//! side needs (the opened bus, the chips' models, the card's image) moves into it at build.
//!
//! ```
//! use driver_api::{BusContext, BusSide};
//! use std::sync::Arc;
//! use std::sync::atomic::{AtomicU64, Ordering};
//! use std::time::Duration;
//!
//! let steps = Arc::new(AtomicU64::new(0));
//! let counted = steps.clone();
//! let bus = BusSide::periodic(Duration::from_millis(1), move || {
//!     counted.fetch_add(1, Ordering::Relaxed);
//! });
//! let registry = Arc::new(device_interface::Registry::new());
//! let runtime = rtt::Runtime::new(registry, Default::default())?;
//! let thread = rtt::ThreadOptions::default();
//! let tasks = bus.add_to(&BusContext::new(&runtime, "card0", &thread))?;
//! assert_eq!(tasks[0].name(), "card0");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! A second `add_to` does not compile: the first took the bus side.
//!
//! ```compile_fail
//! # use driver_api::{BusContext, BusSide};
//! # fn twice(bus: BusSide, ctx: &BusContext<'_>) -> driver_api::BusTasks {
//! bus.add_to(ctx)?;
//! bus.add_to(ctx)
//! # }
//! ```

use crate::card::Card;
use std::time::Duration;

/// What the gateway gives a bus side when it adds it: the runtime, the card's name and
/// the card's thread settings (`thread = { policy, priority, cpus }`).
pub struct BusContext<'a> {
    runtime: &'a rtt::Runtime,
    name: &'a str,
    thread: &'a rtt::ThreadOptions,
}

impl<'a> BusContext<'a> {
    /// Card `name`'s bus side in `runtime`, its activities placed by `thread`.
    pub fn new(
        runtime: &'a rtt::Runtime,
        name: &'a str,
        thread: &'a rtt::ThreadOptions,
    ) -> BusContext<'a> {
        BusContext {
            runtime,
            name,
            thread,
        }
    }

    /// The runtime the bus components go into.
    pub fn runtime(&self) -> &'a rtt::Runtime {
        self.runtime
    }

    /// The card's name: a bus component is usually named after it.
    pub fn name(&self) -> &'a str {
        self.name
    }

    /// Where the card's bus thread runs.
    pub fn thread(&self) -> &'a rtt::ThreadOptions {
        self.thread
    }
}

/// What adding a bus side gives: its components, not started.
pub type BusTasks = Result<Vec<rtt::TaskContext>, rtt::RuntimeError>;

/// A card's bus side, not yet added: the component(s) doing the card's bus I/O, made
/// once, when the gateway calls [`add_to`](Self::add_to).
pub struct BusSide(Box<dyn FnOnce(&BusContext<'_>) -> BusTasks + Send>);

impl BusSide {
    /// A bus side that `add` makes: it adds its component(s) to the context's runtime, on
    /// activities of their own placed by the context's thread settings, not started. The
    /// gateway starts them before the card's IO components and stops them last.
    pub fn new(add: impl FnOnce(&BusContext<'_>) -> BusTasks + Send + 'static) -> BusSide {
        BusSide(Box::new(add))
    }

    /// A bus side of one component, named after the card as a rule.
    pub fn one(
        add: impl FnOnce(&BusContext<'_>) -> Result<rtt::TaskContext, rtt::RuntimeError>
        + Send
        + 'static,
    ) -> BusSide {
        BusSide::new(move |ctx| add(ctx).map(|t| vec![t]))
    }

    /// A bus side stepped once per `period`: [`periodic_bus`] named after the card, on
    /// the card's thread.
    pub fn periodic(period: Duration, step: impl FnMut() + Send + 'static) -> BusSide {
        BusSide::new(move |ctx| {
            periodic_bus(ctx.runtime, ctx.name, period, ctx.thread.clone(), step)
        })
    }

    /// Adds the bus side's components to `ctx`'s runtime, not started. Consumes it: a bus
    /// side is added once.
    pub fn add_to(self, ctx: &BusContext<'_>) -> BusTasks {
        (self.0)(ctx)
    }
}

impl std::fmt::Debug for BusSide {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("BusSide(..)")
    }
}

/// What a driver's build makes of a section: the card, and its bus side when it has one of
/// its own (none for a card whose devices do their own I/O, or one that shares the bus
/// side of another card, as Modbus units on one line do).
pub struct BuiltCard {
    /// The card.
    pub card: Box<dyn Card>,
    /// Its bus side, run once by the gateway.
    pub bus: Option<BusSide>,
}

impl BuiltCard {
    /// `card` with its bus side.
    pub fn new(card: impl Card + 'static, bus: BusSide) -> BuiltCard {
        BuiltCard {
            card: Box::new(card),
            bus: Some(bus),
        }
    }

    /// `card` with no bus side of its own.
    pub fn without_bus(card: impl Card + 'static) -> BuiltCard {
        BuiltCard {
            card: Box::new(card),
            bus: None,
        }
    }
}

/// The bus side of a card stepped once per `period`: a component named `name` on a
/// periodic activity (absolute timing, placed by `thread`) calling `step` each period.
/// What a simulated card or a card polled on a fixed cycle needs; `step` runs on the
/// activity's thread and keeps the real-time contract. See also [`BusSide::periodic`].
pub fn periodic_bus(
    runtime: &rtt::Runtime,
    name: &str,
    period: Duration,
    thread: rtt::ThreadOptions,
    step: impl FnMut() + Send + 'static,
) -> BusTasks {
    let spec = rtt::ActivitySpec::Periodic {
        period,
        thread,
        timing: rtt::Timing::Absolute,
        max_overruns: None,
    };
    let task = runtime.add(name, spec, rtt::InitialState::Stopped, move |_| {
        Ok(Cycle(Box::new(step)))
    })?;
    Ok(vec![task])
}

/// A bus component named `name` on a file-descriptor activity of its own (no timeout,
/// placed by `thread`), not started: what a card woken by its bus's descriptors (a CAN
/// socket, a serial line, GPIO line events) adds from its [`BusSide`]. `build` makes the
/// component over its interface, as [`rtt::Runtime::add`] takes it; the component
/// watches its descriptors from its `start_hook`.
pub fn fd_bus<C: rtt::Component>(
    runtime: &rtt::Runtime,
    name: &str,
    thread: rtt::ThreadOptions,
    build: impl FnOnce(&mut rtt::InterfaceBuilder<C>) -> Result<C, rtt::component::IntrospectError>,
) -> Result<rtt::TaskContext, rtt::RuntimeError> {
    let spec = rtt::ActivitySpec::FileDescriptor {
        timeout: None,
        thread,
    };
    runtime.add(name, spec, rtt::InitialState::Stopped, build)
}

/// Calls its step each period.
struct Cycle(Box<dyn FnMut() + Send>);

impl rtt::Component for Cycle {
    fn update_hook(&mut self, _: &mut rtt::Context<'_>) -> rtt::HookResult {
        (self.0)();
        Ok(())
    }
}

/// What an fd-activity bus component watches of a socket that can be replaced (a CAN
/// interface removed and added again): the descriptor watched and the socket's
/// generation. [`SocketWatch::follow`] watches the current socket and lets go of the old.
#[derive(Debug, Default)]
pub struct SocketWatch {
    watched: Option<(std::os::fd::RawFd, u64)>,
}

impl SocketWatch {
    /// Watches `socket` (of generation `generation`) when it is not the one watched,
    /// letting go of the old; none: nothing is watched. A failed watch is said and tried
    /// again at the next call.
    pub fn follow(
        &mut self,
        ctx: &mut rtt::Context<'_>,
        socket: Option<std::os::fd::BorrowedFd<'_>>,
        generation: u64,
    ) {
        use std::os::fd::AsRawFd;
        let current = socket.map(|fd| (fd.as_raw_fd(), generation));
        if self.watched == current {
            return;
        }
        self.forget(ctx);
        if let Some(fd) = socket {
            match ctx.activity().watch(fd) {
                Ok(()) => self.watched = current,
                Err(e) => tracing::warn!(component = ctx.name(), "cannot watch the socket: {e}"),
            }
        }
    }

    /// Lets go of the socket watched, if any (at stop).
    pub fn forget(&mut self, ctx: &mut rtt::Context<'_>) {
        if let Some((old, _)) = self.watched.take() {
            ctx.activity().unwatch(old);
        }
    }
}
