//! A CAN bus as an rtt component on a file-descriptor activity.
//!
//! A card without J1939 waits in its socket ([`CanBus::wait_and_service`]) at each step and
//! asks for the next step at once, so its activity watches nothing; a J1939 card's watches
//! [`CanBus::fds`]. Either services the bus on every wake-up: received
//! frames are decoded into the card's channels (which the gateway's IO components and any
//! component holding the devices read) and, frame by frame, published on one output port
//! per received message, so a component can see every frame rather than a sample of them.
//! On a real controller, port `controller` carries its state from netlink (error state,
//! error counters, restart delay), written when it changes. An operation `counters` returns
//! the card's counters.
//!
//! ```no_run
//! # use std::sync::Arc;
//! # fn demo(rt: &rtt::Runtime, card: Arc<driver_can::card::CanCard>) -> Result<(), Box<dyn std::error::Error>> {
//! let bus = driver_can::bus::CanBus::open(card)?;
//! let task = driver_can::component::CanIo::add(rt, "can0", bus, Default::default())?;
//! task.start()?;
//! # Ok(()) }
//! ```

use crate::bus::CanBus;
use crate::card::{CanCard, CanCounters};
use crate::netlink::Controller;
use driver_api::SocketWatch;
use rtt::component::IntrospectError;
use rtt::port::OutputPort;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use serde::{Deserialize, Serialize};
use std::os::fd::AsRawFd;
use std::sync::Arc;

/// One received frame as published on its message's port.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CanMessage {
    /// When the kernel received it (CLOCK_MONOTONIC, ns).
    pub received_ns: u64,
    /// When it was written to the port (CLOCK_MONOTONIC, ns).
    pub published_ns: u64,
    /// The physical values of the message's signals, in map order.
    pub values: Vec<f64>,
}

/// The bus component.
pub struct CanIo {
    /// The bus; none until the start opens it when the interface was missing at build.
    bus: Option<CanBus>,
    card: Arc<CanCard>,
    ports: Vec<OutputPort<CanMessage>>,
    sample: CanMessage,
    /// The socket the activity watches.
    watched: SocketWatch,
    /// The J1939 socket the activity watches (J1939 cards).
    watched_j1939: SocketWatch,
    /// A real controller's state, written when it changes.
    controller: OutputPort<Controller>,
    controller_seen: Option<Controller>,
}

impl CanIo {
    /// Adds `bus` to `runtime` as component `name` on a file-descriptor activity of its
    /// own, its thread placed by `thread`; not started.
    pub fn add(
        runtime: &rtt::Runtime,
        name: &str,
        bus: CanBus,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        let card = bus.card().clone();
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            CanIo::new(card, Some(bus), iface)
        })
    }

    /// As [`add`](Self::add) for a card whose interface was not there at build
    /// (`hwgw check` of a deployment before it is installed): the start opens it, and fails
    /// naming it when it is still missing.
    pub fn add_unopened(
        runtime: &rtt::Runtime,
        name: &str,
        card: Arc<CanCard>,
        thread: rtt::ThreadOptions,
    ) -> Result<rtt::TaskContext, rtt::RuntimeError> {
        driver_api::fd_bus(runtime, name, thread, move |iface| {
            CanIo::new(card, None, iface)
        })
    }

    /// Builds the component's interface: port `rx.<message>` per received frame (the DBC
    /// name, or the id in hex), port `controller` and the `counters` operation.
    pub fn new(
        card: Arc<CanCard>,
        bus: Option<CanBus>,
        iface: &mut InterfaceBuilder<CanIo>,
    ) -> Result<CanIo, IntrospectError> {
        let widest = card.map().widest_rx();
        let mut ports = Vec::new();
        for f in card.map().rx() {
            let names: Vec<&str> = f.signals.iter().map(|s| s.name.as_str()).collect();
            ports.push(iface.output_with_sample(
                &format!("rx.{}", f.name),
                &format!(
                    "every received {} frame (id {:#x}): values of {}",
                    f.name,
                    f.id,
                    names.join(", ")
                ),
                CanMessage {
                    values: vec![0.0; f.signals.len()],
                    ..CanMessage::default()
                },
            )?);
        }
        let controller = iface.output(
            "controller",
            "a real controller's state from netlink (error state, error counters, restart \
             delay, bit rate, restarts seen), written when it changes; never on vcan",
        )?;
        if !card.map().isotp().is_empty() {
            isotp_operation(&card, iface)?;
        }
        let c = card.clone();
        iface.client_operation(
            "counters",
            "frame, error and link counters of the bus",
            &[],
            move |()| -> CanCounters { c.counters() },
        )?;
        Ok(CanIo {
            bus,
            card,
            ports,
            sample: CanMessage {
                values: Vec::with_capacity(widest),
                ..CanMessage::default()
            },
            controller,
            controller_seen: None,
            watched: SocketWatch::default(),
            watched_j1939: SocketWatch::default(),
        })
    }
}

/// Operation `request NAME HEX`: one ISO-TP exchange on address pair NAME, the response
/// as hex; one at a time per pair, on the caller's thread (never the bus thread).
fn isotp_operation(
    card: &Arc<CanCard>,
    iface: &mut InterfaceBuilder<CanIo>,
) -> Result<(), IntrospectError> {
    let interface = card.map().interface().to_string();
    let pairs: Vec<(String, can_socket::isotp::IsoTp, std::sync::Mutex<()>)> = card
        .map()
        .isotp()
        .iter()
        .map(|(n, t)| (n.clone(), t.clone(), std::sync::Mutex::new(())))
        .collect();
    let names: Vec<String> = pairs.iter().map(|(n, ..)| n.clone()).collect();
    iface.client_operation(
        "request",
        &format!(
            "sends an ISO-TP request and returns the response (UDS diagnostics), both as \
             hex bytes; address pairs: {}",
            names.join(", ")
        ),
        &[
            ("name", "the address pair"),
            ("request", "the request, hex (e.g. 22F190)"),
        ],
        move |(name, hex): (String, String)| -> Result<String, String> {
            let Some((_, tp, lock)) = pairs.iter().find(|(n, ..)| *n == name) else {
                return Err(format!(
                    "no ISO-TP address pair {name:?} (there are: {})",
                    names.join(", ")
                ));
            };
            let request = parse_hex(&hex)?;
            let _one = lock.lock().unwrap_or_else(|e| e.into_inner());
            let response = tp
                .exchange(&interface, &request)
                .map_err(|e| e.to_string())?;
            Ok(response.iter().map(|b| format!("{b:02X}")).collect())
        },
    )
}

/// Hex bytes (spaces allowed) as bytes.
fn parse_hex(text: &str) -> Result<Vec<u8>, String> {
    let digits: Vec<u8> = text.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
    if !digits.len().is_multiple_of(2) || digits.len() > 2 * can_socket::isotp::MAX_LEN {
        return Err(format!(
            "a request is 1 to {} bytes as pairs of hex digits, not {} digits",
            can_socket::isotp::MAX_LEN,
            digits.len()
        ));
    }
    digits
        .chunks(2)
        .map(|pair| {
            std::str::from_utf8(pair)
                .ok()
                .and_then(|p| u8::from_str_radix(p, 16).ok())
                .ok_or_else(|| format!("{:?} is not a hex byte", String::from_utf8_lossy(pair)))
        })
        .collect()
}

impl CanIo {
    /// Watches the bus's socket when it is not the one watched (the first, or a new one
    /// after the interface was replaced), letting go of the old (the timer steps the bus
    /// at each link check, so a failed watch is tried again).
    fn watch_socket(&mut self, ctx: &mut Context<'_>) {
        if let Some(bus) = &self.bus {
            self.watched
                .follow(ctx, bus.socket_fd(), bus.socket_generation());
            self.watched_j1939
                .follow(ctx, bus.j1939_fd(), bus.j1939_generation());
        }
    }
}

impl Component for CanIo {
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let bus = match &mut self.bus {
            Some(bus) => bus,
            None => self.bus.insert(
                CanBus::open(self.card.clone()).map_err(|e| HookError::new(e.to_string()))?,
            ),
        };
        self.watched.forget(ctx);
        self.watched_j1939.forget(ctx);
        if bus.waits_in_socket() {
            // Each step waits in the socket and asks for the next at once: the activity
            // watches nothing, so it goes from step to step without a call of its own.
            // Every wake-up of the activity (a stop, a trigger, an operation for its
            // thread) ends that wait (see `CanBus::wait_and_service`).
            let card = self.card.clone();
            ctx.activity().on_wake(move || card.wake());
            ctx.activity().wake_at(rtt::time::Timestamp::ZERO)?;
            return Ok(());
        }
        // The timer and the wake-up; the sockets on their own, as they can be replaced.
        for fd in bus.timer_fds() {
            ctx.activity().watch(fd)?;
        }
        self.watch_socket(ctx);
        // Send the first cyclic frames and learn the link state at once.
        self.update_hook(ctx)
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let (ports, sample) = (&mut self.ports, &mut self.sample);
        let Some(bus) = &mut self.bus else {
            return Ok(());
        };
        let mut on_frame = |f: usize, values: &[f64], at: device_interface::time::Timestamp| {
            let Some(port) = ports.get_mut(f) else { return };
            // The card decoded the frame once, for its channels and these values alike.
            sample.values.clear();
            sample.values.extend_from_slice(values);
            sample.received_ns = at.as_nanos();
            sample.published_ns = {
                use device_interface::time::{Clock, MonotonicClock};
                MonotonicClock.now().as_nanos()
            };
            port.write(sample);
        };
        if bus.waits_in_socket() {
            let activity = ctx.activity();
            bus.wait_and_service(&mut || activity.restart_step(), &mut on_frame);
            activity.wake_at(rtt::time::Timestamp::ZERO)?;
        } else {
            bus.service(&mut on_frame);
            self.watch_socket(ctx);
        }
        let c = self.card.controller();
        if c != self.controller_seen {
            if let Some(c) = &c {
                self.controller.write(c);
            }
            self.controller_seen = c;
        }
        Ok(())
    }

    /// In RunTimeError the bus goes on as in Running (a bus that stopped sending and
    /// reading would leave its outputs frozen and its inputs stale-unseen).
    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        if let Err(e) = self.update_hook(ctx) {
            rtt::rt_log!(
                self.card.log(),
                Warn,
                "{}: {}",
                rtt::log::Arg::text(self.card.map().interface()),
                rtt::log::Arg::display(&e)
            );
        }
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if let Some(bus) = &mut self.bus {
            if bus.waits_in_socket() {
                // The thread is joined: no signal or timer may reach a later thread.
                bus.thread_ended();
            } else {
                for fd in bus.timer_fds() {
                    ctx.activity().unwatch(fd.as_raw_fd());
                }
            }
        }
        self.watched.forget(ctx);
        self.watched_j1939.forget(ctx);
    }
}
