//! An I2C card's bus side as an rtt component: a file-descriptor activity with no
//! descriptors, woken at each chip's next poll by its deadline and by the devices' output
//! writes; operation `counters`.
//! Stopping it closes the bus (the chips go offline until it starts again).

use crate::bus::I2cBus;
use crate::card::I2cCounters;
use device_interface::time::{Clock, MonotonicClock};
use rtt::component::IntrospectError;
use rtt::{Component, Context, HookResult, InterfaceBuilder};

/// The bus component.
pub struct I2cIo {
    bus: I2cBus,
}

impl I2cIo {
    /// Adds `bus` to `runtime` as component `name` on an activity of its own, placed by
    /// `thread`; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        bus: I2cBus,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| I2cIo::new(bus, iface))
    }

    /// Builds the interface: operation `counters`.
    pub fn new(bus: I2cBus, iface: &mut InterfaceBuilder<I2cIo>) -> Result<I2cIo, IntrospectError> {
        let card = bus.card().clone();
        iface.client_operation(
            "counters",
            "each chip's state, polls, failed transfers and last error",
            &[],
            move |()| -> I2cCounters { card.counters() },
        )?;
        Ok(I2cIo { bus })
    }
}

impl Component for I2cIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        // Output writes wake this activity, which polls the written chip at once.
        self.bus.card().set_waker(ctx.activity().waker());
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        if let Some(next) = self.bus.step(MonotonicClock.now()) {
            ctx.activity().wake_at(next)?;
        }
        Ok(())
    }

    fn stop_hook(&mut self, _: &mut Context<'_>) {
        self.bus.release();
    }
}
