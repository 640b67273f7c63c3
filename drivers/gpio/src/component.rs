//! A GPIO card's bus side as an rtt component on a file-descriptor activity.
//!
//! Starting the component requests the card's lines (a line another consumer holds fails
//! the start, naming that consumer) and watches one descriptor per chip; every wake-up
//! reads the queued edge events. Each input edge is written to the output port `edges`
//! (connect it buffered to see every one); the `counters` operation returns the card's
//! counters. The lines stay requested when the component stops, at the level the gateway
//! left them, until the process ends. Every [`CHECK_PERIOD`] (a deadline of its activity)
//! it checks that its chips are there; when one goes away it closes its request and looks
//! for it at each deadline until it is back.

use crate::bus::{CHECK_PERIOD, GpioBus, GpioEdge};
use crate::card::GpioCounters;
use device_interface::time::{Clock, MonotonicClock};
use rtt::component::IntrospectError;
use rtt::port::OutputPort;
use rtt::{Component, Context, HookResult, InterfaceBuilder};
use std::os::fd::AsRawFd;

/// The bus component.
pub struct GpioIo {
    bus: GpioBus,
    edges: OutputPort<GpioEdge>,
}

impl GpioIo {
    /// Adds `bus` to `runtime` as component `name` on a file-descriptor activity of its
    /// own, placed by `thread`; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        bus: GpioBus,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| GpioIo::new(bus, iface))
    }

    /// Builds the interface: port `edges` and operation `counters`.
    pub fn new(
        bus: GpioBus,
        iface: &mut InterfaceBuilder<GpioIo>,
    ) -> Result<GpioIo, IntrospectError> {
        let edges = iface.output::<GpioEdge>(
            "edges",
            "every edge of an input line: bit, offset, rising, kernel time (ns), sequence numbers",
        )?;
        let card = bus.card().clone();
        iface.client_operation(
            "counters",
            "edge, lost-event, encoder-error and line-error counters of the card",
            &[],
            move |()| -> GpioCounters { card.counters() },
        )?;
        Ok(GpioIo { bus, edges })
    }
}

impl Component for GpioIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.bus
            .open()
            .map_err(|e| rtt::HookError::new(e.to_string()))?;
        let activity = ctx.activity();
        self.bus.for_each_fd(|fd| activity.watch(fd))?;
        activity.wake_at(MonotonicClock.now().saturating_add(CHECK_PERIOD))?;
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let port = &mut self.edges;
        let mut lost = self.bus.service(&mut |e| port.write(e));
        let deadline = ctx.fd_events().deadline_passed();
        if deadline {
            lost |= self.bus.check_alive();
        }
        let activity = ctx.activity();
        if lost {
            self.bus.close_lost(&mut |fd| {
                activity.unwatch(fd);
            });
        } else if deadline && self.bus.is_missing() {
            self.bus.reopen(&mut |fd| activity.watch(fd));
        }
        if deadline || lost {
            activity.wake_at(MonotonicClock.now().saturating_add(CHECK_PERIOD))?;
        }
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        let activity = ctx.activity();
        let _ = self.bus.for_each_fd(|fd| {
            activity.unwatch(fd.as_raw_fd());
            Ok::<(), ()>(())
        });
    }
}
