//! The [`Card`] trait: one built card, whatever its bus.

use device_interface::CardDevices;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::time::Instant;

use crate::names::ChannelNames;

/// A card's bus status for `hwgw status`: where it is and its counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CardStatus {
    /// Where the card is on its bus: an interface, an address and unit, a port.
    pub bus: String,
    /// The driver's counters and bus state, by name (a serialised snapshot struct).
    pub counters: serde_json::Map<String, serde_json::Value>,
}

impl CardStatus {
    /// A status at `bus` with the fields of `snapshot` (any struct that serialises to a
    /// map) as its counters.
    pub fn new(bus: impl Into<String>, snapshot: &impl Serialize) -> CardStatus {
        let counters = match serde_json::to_value(snapshot) {
            Ok(serde_json::Value::Object(m)) => m,
            Ok(other) => {
                let mut m = serde_json::Map::new();
                m.insert("value".into(), other);
                m
            }
            Err(e) => {
                let mut m = serde_json::Map::new();
                m.insert("error".into(), serde_json::Value::String(e.to_string()));
                m
            }
        };
        CardStatus {
            bus: bus.into(),
            counters,
        }
    }
}

/// What a card's output read-back (`AnalogOut::read_back`, `DigitalOut::check_bit`) shows:
/// the gateway notes an output's value just before hwgw first writes it, to put it back at
/// stop under the policy "initial", only when the read-back is the device's own state.
#[derive(Clone, Default)]
pub enum ReadBack {
    /// Only what hwgw wrote (before that, a placeholder): "initial" leaves such outputs as
    /// they are at stop. The default: a card that cannot tell must not claim more.
    #[default]
    Written,
    /// Always the device's state (the devices are the hardware's registers).
    Device,
    /// The device's state whenever this says so (e.g. once the outputs were polled).
    /// Called from the first write of each output, on the writer's thread: it must keep
    /// the device interfaces' real-time contract (non-blocking, allocation-free).
    DeviceWhen(Arc<dyn Fn() -> bool + Send + Sync>),
}

impl ReadBack {
    /// True when the read-back shows the device's state now.
    pub fn is_device(&self) -> bool {
        match self {
            ReadBack::Written => false,
            ReadBack::Device => true,
            ReadBack::DeviceWhen(now) => now(),
        }
    }
}

impl std::fmt::Debug for ReadBack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ReadBack::Written => "Written",
            ReadBack::Device => "Device",
            ReadBack::DeviceWhen(_) => "DeviceWhen(..)",
        })
    }
}

/// One built card of a deployment.
///
/// Built by its driver's [`BuildFn`](crate::BuildFn) without starting anything (so `hwgw
/// check` runs the same code as `hwgw run`); the gateway then registers its devices, asks
/// for its bus side, and at stop drives its outputs to their safe values.
///
/// Real-time contract: these methods are called by the gateway at build, start, status and
/// stop time, never from a real-time path; the devices they hand out keep the device
/// interfaces' contract (non-blocking, bounded, allocation-free).
pub trait Card: Send + Sync {
    /// The card's devices, registered under the card's name (encoders as
    /// `card.<suffix>`). Called once, at build.
    fn devices(&self) -> CardDevices;

    /// Port names for channels the deployment's `[card.names]` leaves unnamed (e.g. signal
    /// names from a CAN database). Names must be unique per list, without dots or spaces;
    /// give none rather than bad ones. Default: none.
    fn channel_names(&self) -> ChannelNames {
        ChannelNames::default()
    }

    /// What the driver knows of its channels beyond their names (from a CAN database: a
    /// comment, named values), for their ports. Default: nothing.
    fn channel_details(&self) -> crate::ChannelDetails {
        crate::ChannelDetails::default()
    }

    /// Adds the card's bus side to `runtime`: the component(s) doing its bus I/O, on their
    /// own activities, not started. `name` is the card's name (a bus component is usually
    /// named after it). The gateway starts them before the IO components and stops them
    /// last. Default: none (a card whose devices do their own I/O).
    fn add_bus(
        &self,
        runtime: &rtt::Runtime,
        name: &str,
    ) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
        let _ = (runtime, name);
        Ok(Vec::new())
    }

    /// One line for the start-up log: what the card talks to and what it maps.
    fn summary(&self) -> String;

    /// Its bus status and counters, now. Default: none.
    fn status(&self) -> CardStatus {
        CardStatus::default()
    }

    /// What the read-back of its outputs shows (see [`ReadBack`]). Called once, at build.
    /// Default: [`ReadBack::Written`].
    fn read_back(&self) -> ReadBack {
        ReadBack::Written
    }

    /// At stop, after the gateway wrote the safe values to the card's outputs and while its
    /// bus side still runs: waits, until `deadline` at the latest, for them to reach the
    /// hardware (sent, acknowledged). `Err` says why they may not have. Default: nothing
    /// to wait for.
    fn settle(&self, deadline: Instant) -> Result<(), String> {
        let _ = deadline;
        Ok(())
    }
}

/// The bus side of a card stepped once per `period`: a component named `name` on a
/// periodic activity (absolute timing, placed by `thread`) calling `step` each period.
/// What a simulated card or a card polled on a fixed cycle needs; `step` runs on the
/// activity's thread and keeps the real-time contract. Returns it as [`Card::add_bus`] does.
pub fn periodic_bus(
    runtime: &rtt::Runtime,
    name: &str,
    period: std::time::Duration,
    thread: rtt::ThreadOptions,
    step: impl FnMut() + Send + 'static,
) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
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
/// socket, a serial line, GPIO line events) adds in [`Card::add_bus`]. `build` makes the
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
