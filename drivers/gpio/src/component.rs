//! A GPIO card's bus side as an rtt component on a file-descriptor activity.
//!
//! Starting the component requests the card's lines (a line another consumer holds fails
//! the start, naming that consumer) and watches one descriptor per chip; every wake-up
//! reads the queued edge events. Each input edge is written to the output port `edges`
//! (connect it buffered to see every one); the `counters` operation returns the card's
//! counters. The lines stay requested when the component stops, at the level the gateway
//! left them, until the process ends.

use crate::bus::{GpioBus, GpioEdge};
use crate::card::GpioCounters;
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
        self.bus.open().map_err(rtt::HookError::new)?;
        for fd in self.bus.fds() {
            ctx.activity().watch(fd)?;
        }
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let port = &mut self.edges;
        self.bus.service(&mut |e| port.write(e));
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        for fd in self.bus.fds() {
            ctx.activity().unwatch(fd.as_raw_fd());
        }
    }
}
