//! Simulated IO cards: hwgw's embedded default and the mock bus of the test suites.
//!
//! A [`SimCard`] offers every device interface: analog inputs that follow waveforms
//! (constant, sine, ramp, seeded noise) or loop back an analog output, analog outputs,
//! digital inputs looped back from digital outputs, and encoders driven by an analog output
//! as velocity, with turn roll-over, and position switches their travel turns on. Channel counts, ranges and units come from a
//! [`SimConfig`] (the card's section of a hwgw config file).
//!
//! For tests it has hooks a real card lacks: hold an input at a value, move an encoder,
//! force the card stale, offline or into a bus error, and read back a time-ordered record
//! of every output write.
//!
//! Time comes from a [`Clock`](device_interface::time::Clock): with a
//! [`SimClock`](device_interface::time::SimClock) and explicit [`SimCard::step`] calls a
//! test is exact and repeatable.
//!
//! ```
//! use device_interface::time::{SimClock, Timestamp};
//! use device_interface::{AnalogIn, AnalogOut, DigitalIn, DigitalOut, Registry};
//! use driver_sim::{SimCard, SimConfig};
//! use std::sync::Arc;
//! use std::time::Duration;
//!
//! let clock = Arc::new(SimClock::new(Timestamp::ZERO));
//! let card = SimCard::new(&SimConfig::demo(), clock.clone())?;
//! let registry = Registry::new();
//! card.register(&registry, "demo")?;
//!
//! // Analog output 0 loops back to analog input 3; digital outputs to digital inputs.
//! registry.analog_out().lookup("demo")?.write(0, 2.5)?;
//! registry.digital_out().lookup("demo")?.switch_on(6)?;
//! clock.advance(Duration::from_millis(1));
//! card.step();
//! let ai = registry.analog_in().lookup("demo")?;
//! assert!((ai.read(3)? - 2.5).abs() <= ai.resolution(3)?);
//! assert!(registry.digital_in().lookup("demo")?.is_on(6)?);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod card;
pub mod config;
pub mod plugin;
mod record;
mod switch;

pub use card::{SimCard, SimConfigError, SimEncoder, SimFault};
pub use config::SimConfig;
pub use record::{OutputEvent, OutputWrite};
pub use switch::SwitchConfig;
