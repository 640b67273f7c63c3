//! What the GPIO card's kernel tests and its benchmark share: a card built from a section
//! on a gpio-sim chip, and its bus component running.

use device_interface::time::MonotonicClock;
use driver_gpio::bus::GpioBus;
use driver_gpio::card::GpioCard;
use driver_gpio::component::GpioIo;
use driver_gpio::config::GpioConfig;
use kernel_rig::Failed;
use rtt::{Runtime, RuntimeOptions, TaskContext};
use std::sync::Arc;
use testkit::SimChip;

/// The card of section `body` with `chip = "<label of chip>"` first; nothing requested.
pub fn card(chip: &SimChip, body: &str) -> Result<Arc<GpioCard>, Failed> {
    let config: GpioConfig = toml::from_str(&format!("chip = {:?}\n{body}", chip.label))?;
    driver_gpio::plugin::card(&config, Arc::new(MonotonicClock))
        .map_err(|e| Failed::from(format!("{}: {}", e.key.unwrap_or_default(), e.message)))
}

/// A runtime with `card`'s bus component, named "gpio", started (its lines requested).
pub fn running(card: &Arc<GpioCard>) -> Result<(Runtime, TaskContext), Failed> {
    let rt = Runtime::new(
        Arc::new(device_interface::Registry::new()),
        RuntimeOptions::default(),
    )?;
    let task = GpioIo::add(&rt, "gpio", GpioBus::new(card.clone()), Default::default())?;
    task.start()?;
    Ok((rt, task))
}
