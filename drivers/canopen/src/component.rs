//! A CANopen card's bus as an rtt component on a file-descriptor activity: it watches
//! [`CanopenBus::fds`] and services the bus at every wake-up; at its stop (after the
//! gateway settled the safe outputs) the nodes are left in the NMT state the section asks.
//! Operation `counters` returns the card's status: each node's state, NMT state, boot-ups,
//! heartbeats lost, SDO aborts, emergencies with their last codes, and the frame counters.

use crate::bus::CanopenBus;
use crate::card::{CanopenCard, CardSnapshot};
use crate::node::NodeRun;
use driver_api::SocketWatch;
use rtt::component::IntrospectError;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use std::os::fd::AsRawFd;
use std::sync::Arc;

/// The bus, or what opens it at start when the interface was missing at build.
enum Bus {
    Open(Box<CanopenBus>),
    Unopened(Arc<CanopenCard>, Vec<NodeRun>),
    Taken,
}

/// The bus component.
pub struct CanopenIo {
    bus: Bus,
    /// The socket the activity watches.
    watched: SocketWatch,
}

impl CanopenIo {
    /// Adds `bus` to `runtime` as component `name` on a file-descriptor activity of its
    /// own; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        bus: CanopenBus,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            CanopenIo::new(Bus::Open(Box::new(bus)), iface)
        })
    }

    /// As [`add`](Self::add) for a card whose interface was not there at build (`hwgw
    /// check` of a deployment before it is installed): the start opens it, and fails
    /// naming it when it is still missing.
    pub fn add_unopened(
        runtime: &rtt::Runtime,
        name: &str,
        card: Arc<CanopenCard>,
        nodes: Vec<NodeRun>,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            CanopenIo::new(Bus::Unopened(card, nodes), iface)
        })
    }

    /// Builds the component's interface: the `counters` operation.
    fn new(
        bus: Bus,
        iface: &mut InterfaceBuilder<CanopenIo>,
    ) -> Result<CanopenIo, IntrospectError> {
        let card: Option<Arc<CanopenCard>> = match &bus {
            Bus::Open(b) => Some(b.card().clone()),
            Bus::Unopened(card, _) => Some(card.clone()),
            Bus::Taken => None,
        };
        iface.client_operation(
            "counters",
            "the nodes' states (NMT, boot-ups, heartbeats lost, SDO aborts, emergencies \
             with their codes) and the bus's frame counters",
            &[],
            move |()| -> Option<CardSnapshot> { card.as_ref().map(|c| c.snapshot()) },
        )?;
        Ok(CanopenIo {
            bus,
            watched: SocketWatch::default(),
        })
    }

    fn watch_socket(&mut self, ctx: &mut Context<'_>) {
        if let Bus::Open(bus) = &self.bus {
            self.watched
                .follow(ctx, bus.socket_fd(), bus.socket_generation());
        }
    }

    /// Opens the bus when the interface was missing at build: an error naming it when it
    /// still is.
    fn open(&mut self) -> HookResult {
        if !matches!(self.bus, Bus::Unopened(..)) {
            return Ok(());
        }
        if let Bus::Unopened(card, nodes) = std::mem::replace(&mut self.bus, Bus::Taken) {
            match CanopenBus::open(card.clone(), nodes) {
                Ok(bus) => self.bus = Bus::Open(Box::new(bus)),
                Err((e, nodes)) => {
                    self.bus = Bus::Unopened(card, nodes);
                    return Err(HookError::new(e.to_string()));
                }
            }
        }
        Ok(())
    }
}

impl Component for CanopenIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.open()?;
        let Bus::Open(bus) = &self.bus else {
            return Ok(());
        };
        let socket = bus.socket_fd().map(|s| s.as_raw_fd());
        for fd in bus.fds().filter(|fd| Some(fd.as_raw_fd()) != socket) {
            ctx.activity().watch(fd)?;
        }
        self.watched.forget(ctx);
        self.watch_socket(ctx);
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        if let Bus::Open(bus) = &mut self.bus {
            bus.service();
        }
        self.watch_socket(ctx);
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if let Bus::Open(bus) = &mut self.bus {
            bus.stop();
            for fd in bus.fds() {
                ctx.activity().unwatch(fd.as_raw_fd());
            }
        }
        self.watched.forget(ctx);
    }
}
