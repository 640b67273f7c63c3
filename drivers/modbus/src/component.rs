//! A Modbus line as an rtt component: [`LineIo`] polls the units of one connection on a
//! file-descriptor activity of its own, woken at each unit's next due time.
//!
//! Each step polls the units that are due, in order, one request outstanding at a time
//! (each bounded by its unit's timeout), then sends the requests hwgw's Modbus server
//! forwards to the line ([`gateway`](crate::gateway)) — one at least, more while no unit
//! is due, at most [`FORWARDS_PER_STEP`] a step and none begun after [`FORWARD_BUDGET`] but
//! the first — then sets the activity's next wake-up to the earliest next
//! poll (at once while forwarded requests wait). A stop waits for the request under way.
//! An operation `counters` returns every unit's line diagnostics.
//!
//! ```no_run
//! # use std::sync::Arc;
//! # use driver_modbus::line::{LineUnit, Transport};
//! # fn demo(rt: &rtt::Runtime, units: Vec<LineUnit>) -> Result<(), Box<dyn std::error::Error>> {
//! let transport = Transport::Tcp("127.0.0.1:502".parse()?);
//! let line = driver_modbus::component::LineIo::add(rt, "plc", transport, units, Default::default())?;
//! line.start()?;
//! # Ok(()) }
//! ```

use crate::gateway::{Forwarding, Lines};
use crate::line::{LineUnit, Transport, UnitCounters, UnitState, poll_and_schedule};
use device_interface::DeviceError;
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use rtt::component::IntrospectError;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use std::sync::Arc;

/// The most forwarded requests one step sends (then it returns, to be stepped again at
/// once): a stop or an operation never waits behind a long queue.
pub const FORWARDS_PER_STEP: usize = 16;

/// No forwarded request but the step's first is begun once the step has run this long: a
/// stop or an operation waits for the request under way and little more.
pub const FORWARD_BUDGET: std::time::Duration = std::time::Duration::from_millis(20);

/// The poller of one Modbus line.
pub struct LineIo {
    transport: Transport,
    /// Requests forwarded by the server in gateway mode.
    forwarding: Arc<Forwarding>,
    units: Arc<Vec<LineUnit>>,
    states: Vec<UnitState>,
    /// The connection, while open.
    client: Option<crate::client::Client>,
    /// The single-threaded tokio runtime the transactions run on (made at start).
    tokio: Option<tokio::runtime::Runtime>,
    /// Where the line logs: the card's name.
    log: rtt::log::Area,
}

fn now() -> Timestamp {
    MonotonicClock.now()
}

impl LineIo {
    /// Adds the line over `transport` polling `units` to `runtime` as component `name`, on a
    /// file-descriptor activity of its own placed by `thread`; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        transport: Transport,
        units: Vec<LineUnit>,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        let lines = runtime.shared::<Lines>();
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            let line = LineIo::new(transport, units, iface)?;
            lines.register(&line.transport, &line.forwarding);
            Ok(line)
        })
    }

    /// Builds the component's interface: the `counters` operation.
    pub fn new(
        transport: Transport,
        units: Vec<LineUnit>,
        iface: &mut InterfaceBuilder<LineIo>,
    ) -> Result<LineIo, IntrospectError> {
        let units = Arc::new(units);
        let u = units.clone();
        iface.client_operation(
            "counters",
            "line diagnostics of every unit on the line: requests, replies, timeouts, exceptions, transport errors, bad replies, write retries, writes failed, polls",
            &[],
            move |()| -> Vec<UnitCounters> { u.iter().map(UnitCounters::of).collect() },
        )?;
        let t0 = now();
        let log = rtt::log::Area::named(iface.name());
        Ok(LineIo {
            transport,
            forwarding: Arc::new(Forwarding::default()),
            states: units
                .iter()
                .map(|u| UnitState::new(&u.timing, t0, log.clone()))
                .collect(),
            log,
            units,
            client: None,
            tokio: None,
        })
    }
}

impl Component for LineIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        if self.tokio.is_none() {
            self.tokio = Some(
                tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .map_err(|e| HookError::new(format!("cannot make the line's runtime: {e}")))?,
            );
        }
        let t0 = now();
        for (s, u) in self.states.iter_mut().zip(self.units.iter()) {
            *s = UnitState::new(&u.timing, t0, self.log.clone());
        }
        ctx.activity().wake_at(t0)?;
        self.forwarding.open(ctx.activity().waker());
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let Some(tokio) = &self.tokio else {
            return Ok(());
        };
        // Poll every unit that is due now, earliest first; a unit that falls due while
        // another is polled waits for the next step (which comes at once).
        let started = now();
        while let Some((i, due)) = self
            .states
            .iter()
            .enumerate()
            .map(|(i, s)| (i, s.next))
            .filter(|(_, due)| *due <= started)
            .min_by_key(|(_, due)| *due)
        {
            tokio.block_on(poll_and_schedule(
                &mut self.client,
                &self.transport,
                &self.units[i],
                &mut self.states[i],
                due,
                &now,
            ));
        }
        // Then the forwarded requests: at least one (so a unit always due, failing or
        // overrunning its period, cannot starve them), more while no unit is due, within
        // the step's budget.
        let mut forwarded = 0;
        while forwarded < FORWARDS_PER_STEP
            && (forwarded == 0
                || (self.states.iter().all(|s| s.next > now())
                    && now().duration_since(started) < FORWARD_BUDGET))
            && let Some(f) = self.forwarding.take()
        {
            let outcome = tokio.block_on(crate::gateway::forward(
                &mut self.client,
                &self.transport,
                &f,
            ));
            // A master that gave up (its server stopped) is not there to hear it.
            let _ = f.reply.send(outcome);
            forwarded += 1;
        }
        let next = self.states.iter().map(|s| s.next).min();
        if self.forwarding.waiting() {
            ctx.activity().wake_at(now())?;
        } else if let Some(next) = next {
            ctx.activity().wake_at(next)?;
        }
        Ok(())
    }

    fn stop_hook(&mut self, _: &mut Context<'_>) {
        // Forwarded requests are answered 0x0A from now on.
        self.forwarding.close();
        // A new start opens the connection anew.
        self.client = None;
        // Nothing carries the writes still on their way now: their writers hear so.
        for u in self.units.iter() {
            crate::line::fail_pending(
                u,
                &DeviceError::Undelivered {
                    reason: "the Modbus line stopped before the write was sent",
                },
                &self.log,
            );
        }
    }
}
