//! What a driver gets to build a card, and how it says no.

use crate::bus::BuiltCard;
use device_interface::time::Clock;
use std::any::{Any, TypeId};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// A driver's build function: its typed section and the context to a card and its bus
/// side.
pub type BuildFn<C> = fn(&C, &mut CardContext<'_>) -> Result<BuiltCard, CardError>;

/// Why a driver (or a server type) refused its section: a message, and the key under the
/// section it is about when there is one (`rx[0].message`), so the gateway can point at
/// it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct CardError {
    /// Key path under the driver's section, if the problem has one.
    pub key: Option<String>,
    /// What is wrong and what was expected.
    pub message: String,
}

impl CardError {
    /// A problem with the section as a whole.
    pub fn new(message: impl std::fmt::Display) -> CardError {
        CardError {
            key: None,
            message: message.to_string(),
        }
    }

    /// A problem at `key` (a path under the section, e.g. `point[3].address`).
    pub fn at(key: impl Into<String>, message: impl std::fmt::Display) -> CardError {
        CardError {
            key: Some(key.into()),
            message: message.to_string(),
        }
    }
}

/// Everything a driver may use to build one card.
pub struct CardContext<'a> {
    name: &'a str,
    period: Duration,
    base: &'a Path,
    clock: Arc<dyn Clock>,
    shared: &'a mut HashMap<TypeId, Box<dyn Any + Send>>,
    bus_key: Option<String>,
}

impl<'a> CardContext<'a> {
    /// A context for card `name`: its bus period, the folder files are relative to, the
    /// clock, and the deployment's shared driver state. (The card's thread settings go to
    /// its bus side, in its [`BusContext`](crate::BusContext).)
    pub fn new(
        name: &'a str,
        period: Duration,
        base: &'a Path,
        clock: Arc<dyn Clock>,
        shared: &'a mut HashMap<TypeId, Box<dyn Any + Send>>,
    ) -> Self {
        CardContext {
            name,
            period,
            base,
            clock,
            shared,
            bus_key: None,
        }
    }

    /// Says the card shares one bus with the other cards of its driver that give the same
    /// `key` (Modbus units on one line: the line's transport): a reload that rebuilds one
    /// of them, or adds one, rebuilds them all. A card that only *checks* against the
    /// others (two cards claiming one device) shares nothing.
    pub fn shares_bus(&mut self, key: impl Into<String>) {
        self.bus_key = Some(key.into());
    }

    /// What [`shares_bus`](Self::shares_bus) said, if anything.
    pub fn bus_key(&self) -> Option<&str> {
        self.bus_key.as_deref()
    }

    /// The card's name (its devices are registered under it).
    pub fn name(&self) -> &str {
        self.name
    }

    /// The card's bus period (`period_ms`).
    pub fn period(&self) -> Duration {
        self.period
    }

    /// The folder of the deployment file: files a section names are relative to it.
    pub fn resolve(&self, file: &Path) -> std::path::PathBuf {
        self.base.join(file)
    }

    /// The folder of the deployment file.
    pub fn base(&self) -> &Path {
        self.base
    }

    /// The clock devices timestamp with.
    pub fn clock(&self) -> Arc<dyn Clock> {
        self.clock.clone()
    }

    /// State shared by every card built from one deployment, one value per type (created
    /// with `T::default()` at first use): e.g. the Modbus lines several units share.
    pub fn shared<T: Default + Send + 'static>(&mut self) -> &mut T {
        let slot = self
            .shared
            .entry(TypeId::of::<T>())
            .or_insert_with(|| Box::new(T::default()));
        if !slot.is::<T>() {
            // Never: the entry for TypeId::of::<T>() is only ever given a T.
            *slot = Box::new(T::default());
        }
        slot.downcast_mut::<T>()
            .unwrap_or_else(|| unreachable!("the slot holds a T"))
    }
}
