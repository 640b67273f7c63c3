//! The I2C card as an hwgw driver plug-in (`driver = "i2c"`, section
//! [`I2cConfig`]).
//!
//! Building finds the bus (a path, or an adapter's name) and makes each chip's model;
//! nothing is sent until the bus component starts, so `hwgw check` touches no chip.

use crate::bus::I2cBus;
use crate::card::{ChipPlace, I2cCard};
use crate::chips::{self, ChipModel};
use crate::component::I2cIo;
use crate::config::{ChipConfig, I2cConfig};
use device_interface::CardDevices;
use device_interface::time::Clock;
use driver_api::{Card, CardContext, CardError, CardStatus};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

/// The adapters an error lists at most.
const LISTED: usize = 16;

/// The bus `spec` names: a path (anything with a `/`), else an adapter's name.
pub fn find_bus(spec: &str) -> Result<PathBuf, String> {
    if spec.contains('/') {
        let path = Path::new(spec);
        return if path.exists() {
            Ok(path.to_path_buf())
        } else {
            Err(format!("{spec}: no such I2C bus (is i2c-dev loaded?)"))
        };
    }
    let mut adapters = Vec::new();
    if let Ok(dir) = std::fs::read_dir("/sys/class/i2c-dev") {
        for entry in dir.flatten() {
            let dev = entry.file_name().to_string_lossy().to_string();
            let name = std::fs::read_to_string(entry.path().join("name")).unwrap_or_default();
            adapters.push((dev, name.trim().to_string()));
        }
    }
    adapters.sort();
    let found: Vec<&(String, String)> = adapters.iter().filter(|(_, n)| n == spec).collect();
    match found.as_slice() {
        [(dev, _)] => Ok(Path::new("/dev").join(dev)),
        [] if adapters.is_empty() => Err(format!(
            "no I2C adapter is named {spec:?}; there are none (is i2c-dev loaded?)"
        )),
        [] => Err(format!(
            "no I2C adapter is named {spec:?}; the adapters are {}",
            adapters
                .iter()
                .take(LISTED)
                .map(|(d, n)| format!("{d} ({n})"))
                .collect::<Vec<_>>()
                .join(", ")
        )),
        many => Err(format!(
            "{} adapters are named {spec:?} ({}); give the path",
            many.len(),
            many.iter()
                .map(|(d, _)| d.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        )),
    }
}

/// A section built: the card, its chips' models and the bus they are on.
pub struct Built {
    /// The card (its chips offline until polled).
    pub card: Arc<I2cCard>,
    /// The chips' models, in the card's chip order.
    pub models: Vec<Box<dyn ChipModel>>,
    /// The bus's character device.
    pub path: PathBuf,
}

impl Built {
    /// Its bus side.
    pub fn bus(self) -> I2cBus {
        I2cBus::new(self.card, self.models, self.path)
    }
}

/// The card of a section and its chips' models (the bus found, nothing sent).
pub fn card(config: &I2cConfig, clock: Arc<dyn Clock>) -> Result<Built, CardError> {
    config
        .check()
        .map_err(|e| CardError::at(e.key, e.message))?;
    let path = find_bus(&config.bus).map_err(|e| CardError::at("bus", e))?;
    let models: Vec<Box<dyn ChipModel>> = config.chip.iter().map(chips::model).collect();
    let mut initial = Vec::new();
    for c in &config.chip {
        if let ChipConfig::Mcp23017(m) = c {
            initial.extend(m.outputs.iter().map(|p| m.initial_on.contains(p)));
        }
    }
    let places: Vec<ChipPlace> = config
        .chip
        .iter()
        .zip(&models)
        .map(|(c, m)| ChipPlace {
            address: c.address(),
            poll_ms: c.poll_ms(),
            model: m.model(),
            shape: m.shape(),
            analog_in: m.analog_in(),
            analog_out: m
                .analog_out()
                .into_iter()
                .map(|scale| {
                    let volts = match c {
                        ChipConfig::Mcp4725(d) => d.initial_v,
                        _ => 0.0,
                    };
                    (scale, scale.to_raw_saturating(volts))
                })
                .collect(),
            encoders: m.encoders(),
        })
        .collect();
    let card =
        Arc::new(I2cCard::new(&places, &initial, clock).map_err(|e| CardError::at("chip", e))?);
    Ok(Built { card, models, path })
}

struct I2cPlugin {
    card: Arc<I2cCard>,
    /// Taken by `add_bus` (once).
    models: Mutex<Option<Vec<Box<dyn ChipModel>>>>,
    path: PathBuf,
    thread: rtt::ThreadOptions,
}

/// Builds the card a section describes.
pub fn build(config: &I2cConfig, ctx: &mut CardContext<'_>) -> Result<Box<dyn Card>, CardError> {
    let Built { card, models, path } = card(config, ctx.clock())?;
    Ok(Box::new(I2cPlugin {
        card,
        models: Mutex::new(Some(models)),
        path,
        thread: ctx.thread().clone(),
    }))
}

impl Card for I2cPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    fn add_bus(
        &self,
        runtime: &rtt::Runtime,
        name: &str,
    ) -> Result<Vec<rtt::TaskContext>, rtt::RuntimeError> {
        let models = self
            .models
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
            .unwrap_or_default();
        let bus = I2cBus::new(self.card.clone(), models, self.path.clone());
        Ok(vec![I2cIo::add(runtime, name, bus, self.thread.clone())?])
    }

    fn summary(&self) -> String {
        let chips: Vec<String> = self
            .card
            .chips()
            .iter()
            .map(|c| format!("{} at {:#04x} every {} ms", c.model, c.address, c.poll_ms))
            .collect();
        format!("{}: {}", self.path.display(), chips.join(", "))
    }

    fn settle(&self, deadline: std::time::Instant) -> Result<(), String> {
        self.card.settle(deadline)
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.path.display().to_string(), &self.card.counters())
    }
}
