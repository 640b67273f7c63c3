//! A Firmata card's bus side as an rtt component: a file-descriptor activity watching the
//! serial line (the descriptor changes at each reopen), woken by its deadlines (hand-shake
//! phases, probes, reopen) and by the devices' output writes; operation `counters`.
//!
//! Its start waits for the board's hand-shake (at most `banner_ms` plus the replies'
//! waits): a board that answers but lacks what the section asks for fails the start with
//! the reason; a board that is not there leaves the card offline, opened again and again.
//! Stopping it closes the port.

use crate::bus::{FirmataBus, Outcome, REPLY_WAIT, REPORT_WAIT};
use crate::card::FirmataCounters;
use device_interface::time::{Clock, MonotonicClock};
use rtt::component::IntrospectError;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};

/// The bus component.
pub struct FirmataIo {
    bus: FirmataBus,
    /// The descriptor watched and the line generation it belongs to.
    watched: Option<(RawFd, u64)>,
}

impl FirmataIo {
    /// Adds `bus` to `runtime` as component `name` on an activity of its own, placed by
    /// `thread`; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        bus: FirmataBus,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            FirmataIo::new(bus, iface)
        })
    }

    /// Builds the interface: operation `counters`.
    pub fn new(
        bus: FirmataBus,
        iface: &mut InterfaceBuilder<FirmataIo>,
    ) -> Result<FirmataIo, IntrospectError> {
        let card = bus.card().clone();
        iface.client_operation(
            "counters",
            "the line's state and diagnostics: bytes, messages, framing errors, unknown commands, resyncs, opens, reopens, probes",
            &[],
            move |()| -> FirmataCounters { card.counters() },
        )?;
        Ok(FirmataIo { bus, watched: None })
    }

    /// Watches the line's current descriptor (a new one after a reopen).
    fn rewatch(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let now = self.bus.fd().map(|(fd, g)| (fd.as_raw_fd(), g));
        if now == self.watched {
            return Ok(());
        }
        if let Some((old, _)) = self.watched.take() {
            ctx.activity().unwatch(old);
        }
        if let Some((fd, _)) = self.bus.fd() {
            ctx.activity().watch(fd)?;
        }
        self.watched = now;
        Ok(())
    }

    /// Steps the hand-shake until the board is online, refused or given up on.
    fn wait_for_board(&mut self) -> Result<(), String> {
        let limit = Duration::from_millis(u64::from(self.bus.card().config().banner_ms))
            + REPLY_WAIT * 2
            + REPORT_WAIT;
        let end = Instant::now() + limit;
        loop {
            let (outcome, next) = self.bus.step(MonotonicClock.now());
            match outcome {
                Outcome::Online | Outcome::Closed => return Ok(()),
                Outcome::Refused(why) => return Err(why),
                Outcome::Pending => {}
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(());
            }
            let until = Duration::from_nanos(
                next.as_nanos()
                    .saturating_sub(MonotonicClock.now().as_nanos()),
            );
            let wait = until.min(left).min(Duration::from_millis(100));
            if let Some((fd, _)) = self.bus.fd() {
                let mut p = [nix::poll::PollFd::new(fd, nix::poll::PollFlags::POLLIN)];
                let ms = u16::try_from(wait.as_millis()).unwrap_or(100);
                let _ = nix::poll::poll(&mut p, nix::poll::PollTimeout::from(ms));
            } else {
                std::thread::sleep(wait);
            }
        }
    }
}

impl Component for FirmataIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        // Output writes wake this activity, which sends them at once.
        self.bus.card().set_waker(ctx.activity().waker());
        // A start asked for (again) tries a board refused before.
        self.bus.forget_refusal();
        self.wait_for_board().map_err(HookError::new)?;
        self.rewatch(ctx)?;
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let (_, next) = self.bus.step(MonotonicClock.now());
        self.rewatch(ctx)?;
        ctx.activity().wake_at(next)?;
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if let Some((fd, _)) = self.watched.take() {
            ctx.activity().unwatch(fd);
        }
        self.bus.release();
    }
}
