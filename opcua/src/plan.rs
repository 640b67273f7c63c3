//! What the server serves, gathered when it is built: the chosen devices' channels (each
//! with its card, IO component and port), and every component of the runtime with its
//! ports and operations.

use crate::config::OpcuaConfig;
use device_interface::{Interface, Registry};
use driver_api::CardError;
use driver_api::channels::{self, Channel};
use rtt::TaskContext;

/// A served device: an IO component's channels.
#[derive(Clone)]
pub(crate) struct Device {
    /// Its card (the registry name's owner).
    pub card: String,
    /// Its name under the card in the address space (`ai`, or the whole component
    /// name for a device not named after its card).
    pub label: String,
    /// Its IO component.
    pub component: String,
    /// Its registry interface and name, for its health.
    pub interface: Interface,
    /// Its registry name.
    pub name: String,
    /// Its IO component, when the runtime has it.
    pub task: Option<TaskContext>,
    /// Its channels.
    pub channels: Vec<Channel>,
}

/// Everything served.
#[derive(Clone)]
pub(crate) struct Plan {
    /// The devices, in registry order.
    pub devices: Vec<Device>,
    /// The components of the runtime served: all but the IO components of devices left
    /// out.
    pub components: Vec<TaskContext>,
    /// The served IO components that drive outputs (analog and digital outputs, encoders):
    /// their operations write outputs past the checks of a write.
    pub drives_outputs: Vec<String>,
}

impl Plan {
    /// True when `component.port` is a served channel.
    pub(crate) fn is_channel(&self, component: &str, port: &str) -> bool {
        self.devices
            .iter()
            .filter(|d| d.component == component)
            .any(|d| d.channels.iter().any(|c| c.port == port))
    }

    /// The number of channels.
    pub(crate) fn channel_count(&self) -> usize {
        self.devices.iter().map(|d| d.channels.len()).sum()
    }
}

/// The plan of a section over `registry` and the runtime; every problem.
pub(crate) fn plan(
    c: &OpcuaConfig,
    registry: &Registry,
    rt: &rtt::Runtime,
) -> Result<Plan, Vec<CardError>> {
    let (entries, missing) = channels::devices(registry, &c.devices);
    let mut problems: Vec<CardError> = missing
        .into_iter()
        .map(|(i, why)| CardError::at(format!("devices[{i}]"), why))
        .collect();
    let mut devices = Vec::new();
    for e in &entries {
        let found = match channels::of_device(registry, rt, e.interface, &e.info.name) {
            Ok(c) => c,
            Err(why) => {
                problems.push(CardError::new(why));
                continue;
            }
        };
        let Some(component) = found.first().map(|c| c.component.clone()) else {
            continue;
        };
        let card = e.info.owner.clone();
        let label = component
            .strip_prefix(card.as_str())
            .and_then(|r| r.strip_prefix('.'))
            .filter(|r| !r.is_empty())
            .unwrap_or(&component)
            .to_string();
        devices.push(Device {
            card,
            label,
            task: rt.component(&component).ok(),
            component,
            interface: e.interface,
            name: e.info.name.clone(),
            channels: found,
        });
    }
    // The IO components of devices not served are not served either.
    let (all, _) = channels::devices(registry, &[]);
    let hidden: Vec<String> = all
        .iter()
        .filter_map(|e| channels::io_component(e.interface, &e.info.name))
        .map(|(c, _)| c)
        .filter(|c| !devices.iter().any(|d| &d.component == c))
        .collect();
    let components = rt
        .components()
        .into_iter()
        .filter(|t| !hidden.iter().any(|h| h == t.name()))
        .collect();
    let drives_outputs = devices
        .iter()
        .filter(|d| {
            matches!(
                d.interface,
                Interface::AnalogOut | Interface::DigitalOut | Interface::Encoder
            )
        })
        .map(|d| d.component.clone())
        .collect();
    if problems.is_empty() {
        Ok(Plan {
            devices,
            components,
            drives_outputs,
        })
    } else {
        Err(problems)
    }
}
