//! Driver types by name: what `driver = "…"` in a deployment may say.
//!
//! Each entry is a driver's build function over its typed section (see
//! [`driver_api`]); the section is parsed strictly from the deployment file where it
//! stands, so its errors point at the file, line and key. hwgw ships `sim`, `modbus`,
//! `socketcan`, `gpio`, `i2c`, `comedi` and `firmata`; a user's binary adds its own with [`DriverTypes::register`] (see
//! `examples/custom-driver`).

use driver_api::{BuildFn, BuiltCard, CardContext, CardError};
use serde::de::DeserializeOwned;
use std::collections::BTreeMap;
use std::ops::Range;
use std::sync::Arc;
use toml::Spanned;
use toml::de::DeValue;

/// Why a section did not make a card.
pub(crate) enum SectionError {
    /// The section does not parse into the driver's section type: the key path under the
    /// section, where in the file, and what was expected.
    Parse {
        path: String,
        span: Option<Range<usize>>,
        message: String,
    },
    /// The driver refused it.
    Card(CardError),
}

/// A driver with its section type erased.
pub(crate) trait DriverEntry: Send + Sync {
    /// Parses `section` and builds the card and its bus side.
    fn build(
        &self,
        section: Spanned<DeValue<'_>>,
        ctx: &mut CardContext<'_>,
    ) -> Result<BuiltCard, SectionError>;
}

/// Parses a section (a card's driver section, a server's) strictly into its type `C`;
/// only [`SectionError::Parse`], located where the section stands in the file.
pub(crate) fn parse<C: DeserializeOwned>(section: Spanned<DeValue<'_>>) -> Result<C, SectionError> {
    let de = toml::de::ValueDeserializer::from(section);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        SectionError::Parse {
            path: if path == "." { String::new() } else { path },
            span: inner.span(),
            message: inner.message().trim().to_string(),
        }
    })
}

struct Typed<C>(BuildFn<C>);

impl<C: DeserializeOwned + 'static> DriverEntry for Typed<C> {
    fn build(
        &self,
        section: Spanned<DeValue<'_>>,
        ctx: &mut CardContext<'_>,
    ) -> Result<BuiltCard, SectionError> {
        let config: C = parse(section)?;
        (self.0)(&config, ctx).map_err(SectionError::Card)
    }
}

/// Driver types by name.
#[derive(Clone)]
pub struct DriverTypes {
    types: BTreeMap<String, Arc<dyn DriverEntry>>,
}

impl DriverTypes {
    /// No drivers.
    pub fn empty() -> Self {
        DriverTypes {
            types: BTreeMap::new(),
        }
    }

    /// The drivers built into hwgw: canopen, comedi, firmata, gpio, i2c, modbus, sim,
    /// socketcan.
    pub fn builtin() -> Self {
        let mut t = Self::empty();
        t.register("sim", driver_sim::plugin::build);
        t.register("modbus", driver_modbus::plugin::build);
        t.register("socketcan", driver_can::plugin::build);
        t.register("canopen", driver_canopen::plugin::build);
        t.register("gpio", driver_gpio::plugin::build);
        t.register("i2c", driver_i2c::plugin::build);
        t.register("comedi", driver_comedi::plugin::build);
        t.register("firmata", driver_serial::plugin::build);
        t
    }

    /// Adds driver `name`, built by `build` from its section (type `C`, parsed strictly);
    /// a name already taken is refused (returns false).
    pub fn register<C: DeserializeOwned + 'static>(
        &mut self,
        name: &str,
        build: BuildFn<C>,
    ) -> bool {
        if self.types.contains_key(name) {
            return false;
        }
        self.types.insert(name.to_string(), Arc::new(Typed(build)));
        true
    }

    /// The driver names, sorted.
    pub fn names(&self) -> Vec<&str> {
        self.types.keys().map(String::as_str).collect()
    }

    /// True when `name` is a driver of this build.
    pub fn contains(&self, name: &str) -> bool {
        self.types.contains_key(name)
    }

    pub(crate) fn get(&self, name: &str) -> Option<&dyn DriverEntry> {
        self.types.get(name).map(|d| &**d)
    }
}
