//! The hwgw device interfaces: what every driver implements and every component uses.
//!
//! The five physical interfaces of the Orocos Hardware Device Interface — [`AnalogIn`],
//! [`AnalogOut`], [`DigitalIn`], [`DigitalOut`], [`Encoder`] — as Rust traits, with:
//!
//! - [`DeviceError`], the one error type of every device method, and [`Health`], each
//!   device's online/stale/offline status and the age of its last good sample;
//! - [`Scale`], the shared raw-to-physical conversion (drivers deal in raw values);
//! - [`bits`], inclusive bit spans and lock-free bit images for digital devices;
//! - [`encoder`], the shared position/turn arithmetic;
//! - [`logical`], the logical devices over them — [`Sensor`](logical::Sensor),
//!   [`Drive`](logical::Drive), [`Axis`](logical::Axis) with homing (manual L5824–5876);
//! - [`Registry`], name serving per interface ("no type-casting whatsoever");
//! - [`channel`], single-channel handles with optional inversion;
//! - [`time`], monotonic timestamps and a simulated clock;
//! - [`text`], values as error messages show them (short numbers, cut strings);
//! - [`Delivery`], where a write stands that a bus carries after the call returned;
//! - `conformance` (feature `conformance`), the kit every driver's tests run.
//!
//! Every trait method may run on a real-time thread: non-blocking, bounded, allocation-free.
//!
//! ```
//! use device_interface::{AnalogIn, Registry};
//!
//! fn report_pressure(registry: &Registry) -> Result<f64, Box<dyn std::error::Error>> {
//!     let card = registry.analog_in().lookup("press.adc")?;
//!     Ok(card.read(3)?)
//! }
//! ```

pub mod bits;
pub mod channel;
#[cfg(feature = "conformance")]
pub mod conformance;
mod delivery;
pub mod encoder;
mod error;
mod health;
mod interfaces;
pub mod logical;
mod registry;
mod scale;
pub mod text;
pub mod time;

pub use delivery::{Delivery, DeliveryTracker};
pub use error::DeviceError;
pub use health::{Health, Status};
pub use interfaces::{
    AnalogIn, AnalogOut, AnalogReference, Device, DigitalIn, DigitalOut, Encoder,
};
pub use registry::{
    CardDevices, Interface, NameInfo, NameServer, Registry, RegistryEntry, RegistryError, Served,
};
pub use scale::{AnalogRange, Linear, RawRange, Scale, ScaleError, Unit, linear};
