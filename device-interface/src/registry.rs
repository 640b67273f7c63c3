//! Name serving: find a device by name, per interface, without type-casting.
//!
//! A [`NameServer<T>`] maps names to `Arc<T>` for one interface; a [`Registry`] gathers one
//! per interface. A card registers each interface it provides under its name (one card may
//! appear under several interfaces); components look devices up by name. There is no hidden
//! global: whoever needs the registry is handed it.
//!
//! Lookups are lock-free (the table is swapped as a whole when a name is added or removed,
//! which is rare), so a lookup can run on a real-time thread, though the usual pattern is to
//! look a device up once when a component is configured and keep the `Arc`.
//!
//! ```
//! use device_interface::{Registry, DigitalOut};
//! # use device_interface::{Device, DeviceError, Health, Status, time::Timestamp};
//! # struct Relay;
//! # impl Device for Relay { fn health(&self) -> Health { Health { status: Status::Online, last_good: None, checked_at: Timestamp::ZERO, last_error: None } } }
//! # impl DigitalOut for Relay {
//! #     fn output_count(&self) -> u32 { 8 }
//! #     fn set_bit(&self, _: u32, _: bool) -> Result<(), DeviceError> { Ok(()) }
//! #     fn check_bit(&self, _: u32) -> Result<bool, DeviceError> { Ok(false) }
//! # }
//! use std::sync::Arc;
//!
//! let registry = Registry::new();
//! registry.digital_out().register("relays", "card0", Arc::new(Relay))?;
//! registry.digital_out().alias("ThreadScope", "relays")?;
//!
//! let scope = registry.digital_out().lookup("ThreadScope")?;
//! scope.switch_on(0)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::logical::{Axis, Drive, Sensor};
use crate::{AnalogIn, AnalogOut, DigitalIn, DigitalOut, Encoder};
use arc_swap::ArcSwap;
use std::collections::HashMap;
use std::fmt;
use std::sync::{Arc, Mutex, MutexGuard};

/// The five device interfaces, for naming them in lists and errors.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Interface {
    /// [`AnalogIn`]
    AnalogIn,
    /// [`AnalogOut`]
    AnalogOut,
    /// [`DigitalIn`]
    DigitalIn,
    /// [`DigitalOut`]
    DigitalOut,
    /// [`Encoder`]
    Encoder,
    /// A [`Sensor<f64>`](crate::logical::Sensor), logical.
    Sensor,
    /// A [`Drive`](crate::logical::Drive), logical.
    Drive,
    /// An [`Axis`](crate::logical::Axis), logical.
    Axis,
}

impl Interface {
    /// The five physical interfaces, in a fixed order (cards offer these; the logical ones
    /// are [`LOGICAL`](Self::LOGICAL)).
    pub const ALL: [Interface; 5] = [
        Interface::AnalogIn,
        Interface::AnalogOut,
        Interface::DigitalIn,
        Interface::DigitalOut,
        Interface::Encoder,
    ];

    /// The logical interfaces, built over physical devices ([`crate::logical`]).
    pub const LOGICAL: [Interface; 3] = [Interface::Sensor, Interface::Drive, Interface::Axis];

    /// True for a logical interface.
    pub fn is_logical(self) -> bool {
        Self::LOGICAL.contains(&self)
    }
}

impl fmt::Display for Interface {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Interface::AnalogIn => "AnalogIn",
            Interface::AnalogOut => "AnalogOut",
            Interface::DigitalIn => "DigitalIn",
            Interface::DigitalOut => "DigitalOut",
            Interface::Encoder => "Encoder",
            Interface::Sensor => "Sensor",
            Interface::Drive => "Drive",
            Interface::Axis => "Axis",
        })
    }
}

/// Why a name could not be registered, aliased or found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RegistryError {
    /// The name is taken.
    #[error(
        "{interface} name {name:?} is already registered by {existing_owner:?}; {new_owner:?} cannot register it too"
    )]
    Duplicate {
        /// Interface of the name server.
        interface: Interface,
        /// The contested name.
        name: String,
        /// Who holds the name now.
        existing_owner: String,
        /// Who asked for it.
        new_owner: String,
    },
    /// No device of that name.
    #[error("no {interface} named {name:?}; registered: {}", known_text(.known))]
    NotFound {
        /// Interface of the name server.
        interface: Interface,
        /// The name asked for.
        name: String,
        /// The names that do exist, sorted.
        known: Vec<String>,
    },
    /// The name cannot be used.
    #[error("invalid device name {name:?}: {reason}")]
    InvalidName {
        /// The refused name.
        name: String,
        /// Why.
        reason: &'static str,
    },
}

fn known_text(known: &[String]) -> String {
    if known.is_empty() {
        "none".to_string()
    } else {
        known.join(", ")
    }
}

/// One registered name, as listed by [`NameServer::names`].
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct NameInfo {
    /// The name.
    pub name: String,
    /// Who registered the device (a card name).
    pub owner: String,
    /// For an alias, the name it stands for.
    pub alias_of: Option<String>,
}

struct Entry<T: ?Sized> {
    device: Arc<T>,
    owner: Arc<str>,
    alias_of: Option<Arc<str>>,
}

impl<T: ?Sized> Clone for Entry<T> {
    fn clone(&self) -> Self {
        Entry {
            device: Arc::clone(&self.device),
            owner: Arc::clone(&self.owner),
            alias_of: self.alias_of.clone(),
        }
    }
}

type Table<T> = HashMap<Arc<str>, Entry<T>>;

/// Names to devices of one interface `T` (a trait object such as `dyn AnalogIn`).
///
/// Thread-safe. Lookups take no lock; changes are serialised and replace the table.
pub struct NameServer<T: ?Sized> {
    interface: Interface,
    table: ArcSwap<Table<T>>,
    writer: Mutex<()>,
}

impl<T: ?Sized> NameServer<T> {
    /// An empty name server for `interface`.
    pub fn new(interface: Interface) -> Self {
        NameServer {
            interface,
            table: ArcSwap::from_pointee(HashMap::new()),
            writer: Mutex::new(()),
        }
    }

    /// The interface this server names.
    pub fn interface(&self) -> Interface {
        self.interface
    }

    /// Registers `device` as `name`, owned by `owner` (the card that provides it).
    ///
    /// Errors: [`RegistryError::Duplicate`] naming both owners when `name` is taken (as a
    /// name or an alias); [`RegistryError::InvalidName`] for an empty name or one with white
    /// space or control characters.
    pub fn register(&self, name: &str, owner: &str, device: Arc<T>) -> Result<(), RegistryError> {
        check_name(name)?;
        self.change(|table| {
            self.check_free(table, name, owner)?;
            table.insert(
                Arc::from(name),
                Entry {
                    device,
                    owner: Arc::from(owner),
                    alias_of: None,
                },
            );
            Ok(())
        })
    }

    /// Makes `alias` another name for the device registered as `target`. An alias of an
    /// alias names the original device. Removing the target removes its aliases.
    pub fn alias(&self, alias: &str, target: &str) -> Result<(), RegistryError> {
        check_name(alias)?;
        self.change(|table| {
            let entry = table
                .get(target)
                .cloned()
                .ok_or_else(|| self.not_found(table, target))?;
            let original = entry.alias_of.clone().unwrap_or_else(|| Arc::from(target));
            self.check_free(table, alias, &format!("an alias of {original}"))?;
            table.insert(
                Arc::from(alias),
                Entry {
                    alias_of: Some(original),
                    ..entry
                },
            );
            Ok(())
        })
    }

    /// The device named `name`, or `None`. Lock-free.
    pub fn get(&self, name: &str) -> Option<Arc<T>> {
        self.table.load().get(name).map(|e| Arc::clone(&e.device))
    }

    /// The device named `name`, or [`RegistryError::NotFound`] listing the names that exist.
    pub fn lookup(&self, name: &str) -> Result<Arc<T>, RegistryError> {
        let table = self.table.load();
        match table.get(name) {
            Some(e) => Ok(Arc::clone(&e.device)),
            None => Err(self.not_found(&table, name)),
        }
    }

    /// True when `name` is registered (as a name or an alias).
    pub fn contains(&self, name: &str) -> bool {
        self.table.load().contains_key(name)
    }

    /// Removes `name`. Removing a name also removes its aliases; removing an alias removes
    /// only the alias. Returns every name removed, sorted.
    pub fn unregister(&self, name: &str) -> Result<Vec<String>, RegistryError> {
        self.change(|table| {
            let entry = table
                .get(name)
                .cloned()
                .ok_or_else(|| self.not_found(table, name))?;
            let removed = if entry.alias_of.is_some() {
                vec![Arc::from(name)]
            } else {
                table
                    .iter()
                    .filter(|(k, e)| &***k == name || e.alias_of.as_deref() == Some(name))
                    .map(|(k, _)| Arc::clone(k))
                    .collect()
            };
            Ok(remove_all(table, removed))
        })
    }

    /// Removes every name `owner` registered, with their aliases. Returns the names removed,
    /// sorted (empty when the owner had none).
    pub fn unregister_owner(&self, owner: &str) -> Vec<String> {
        let result = self.change(|table| {
            let mine: Vec<Arc<str>> = table
                .iter()
                .filter(|(_, e)| e.alias_of.is_none() && &*e.owner == owner)
                .map(|(k, _)| Arc::clone(k))
                .collect();
            let removed: Vec<Arc<str>> = table
                .iter()
                .filter(|(k, e)| {
                    mine.contains(k) || e.alias_of.as_ref().is_some_and(|t| mine.contains(t))
                })
                .map(|(k, _)| Arc::clone(k))
                .collect();
            Ok(remove_all(table, removed))
        });
        result.unwrap_or_default()
    }

    /// Every registered name with its owner, sorted by name.
    pub fn names(&self) -> Vec<NameInfo> {
        let mut v: Vec<NameInfo> = self
            .table
            .load()
            .iter()
            .map(|(k, e)| NameInfo {
                name: k.to_string(),
                owner: e.owner.to_string(),
                alias_of: e.alias_of.as_ref().map(|a| a.to_string()),
            })
            .collect();
        v.sort_by(|a, b| a.name.cmp(&b.name));
        v
    }

    /// Number of names, aliases included.
    pub fn len(&self) -> usize {
        self.table.load().len()
    }

    /// True when nothing is registered.
    pub fn is_empty(&self) -> bool {
        self.table.load().is_empty()
    }

    fn change<R>(
        &self,
        f: impl FnOnce(&mut Table<T>) -> Result<R, RegistryError>,
    ) -> Result<R, RegistryError> {
        let _guard = self.lock();
        let mut table: Table<T> = (**self.table.load()).clone();
        let r = f(&mut table)?;
        self.table.store(Arc::new(table));
        Ok(r)
    }

    fn lock(&self) -> MutexGuard<'_, ()> {
        // The guarded data is `()`: a panic elsewhere cannot have left it inconsistent.
        self.writer.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn check_free(&self, table: &Table<T>, name: &str, owner: &str) -> Result<(), RegistryError> {
        match table.get(name) {
            None => Ok(()),
            Some(e) => Err(RegistryError::Duplicate {
                interface: self.interface,
                name: name.to_string(),
                existing_owner: match &e.alias_of {
                    Some(t) => format!("an alias of {t}"),
                    None => e.owner.to_string(),
                },
                new_owner: owner.to_string(),
            }),
        }
    }

    fn not_found(&self, table: &Table<T>, name: &str) -> RegistryError {
        let mut known: Vec<String> = table.keys().map(|k| k.to_string()).collect();
        known.sort();
        RegistryError::NotFound {
            interface: self.interface,
            name: name.to_string(),
            known,
        }
    }
}

fn remove_all<T: ?Sized>(table: &mut Table<T>, names: Vec<Arc<str>>) -> Vec<String> {
    let mut out: Vec<String> = names
        .into_iter()
        .filter_map(|k| table.remove(&k).map(|_| k.to_string()))
        .collect();
    out.sort();
    out
}

fn check_name(name: &str) -> Result<(), RegistryError> {
    let reason = if name.is_empty() {
        "a name cannot be empty"
    } else if name.chars().any(|c| c.is_whitespace() || c.is_control()) {
        "a name cannot contain white space or control characters"
    } else {
        return Ok(());
    };
    Err(RegistryError::InvalidName {
        name: name.to_string(),
        reason,
    })
}

/// The devices one card offers, for [`Registry::register_card`].
#[derive(Default)]
pub struct CardDevices {
    /// Its analog inputs, if it has any.
    pub analog_in: Option<Arc<dyn AnalogIn>>,
    /// Its analog outputs.
    pub analog_out: Option<Arc<dyn AnalogOut>>,
    /// Its digital inputs.
    pub digital_in: Option<Arc<dyn DigitalIn>>,
    /// Its digital outputs.
    pub digital_out: Option<Arc<dyn DigitalOut>>,
    /// Its encoders, each with the suffix of its name (`card.suffix`).
    pub encoders: Vec<(String, Arc<dyn Encoder>)>,
    /// Its drives (a CANopen CiA 402 node), each with the suffix of its name
    /// (`card.suffix`), registered as logical [`Drive`]s.
    pub drives: Vec<(String, Arc<dyn Drive>)>,
}

/// One name in a [`Registry`] listing.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct RegistryEntry {
    /// Which interface the name is served under.
    pub interface: Interface,
    /// The name, owner and alias target.
    #[serde(flatten)]
    pub info: NameInfo,
}

/// One name server per device interface.
///
/// Built once at start-up and shared as `Arc<Registry>` with every component that needs
/// devices.
pub struct Registry {
    analog_in: NameServer<dyn AnalogIn>,
    analog_out: NameServer<dyn AnalogOut>,
    digital_in: NameServer<dyn DigitalIn>,
    digital_out: NameServer<dyn DigitalOut>,
    encoder: NameServer<dyn Encoder>,
    sensor: NameServer<dyn Sensor<f64>>,
    drive: NameServer<dyn Drive>,
    axis: NameServer<dyn Axis>,
}

impl Default for Registry {
    fn default() -> Self {
        Self::new()
    }
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Registry {
            analog_in: NameServer::new(Interface::AnalogIn),
            analog_out: NameServer::new(Interface::AnalogOut),
            digital_in: NameServer::new(Interface::DigitalIn),
            digital_out: NameServer::new(Interface::DigitalOut),
            encoder: NameServer::new(Interface::Encoder),
            sensor: NameServer::new(Interface::Sensor),
            drive: NameServer::new(Interface::Drive),
            axis: NameServer::new(Interface::Axis),
        }
    }

    /// Analog inputs by name.
    pub fn analog_in(&self) -> &NameServer<dyn AnalogIn> {
        &self.analog_in
    }

    /// Analog outputs by name.
    pub fn analog_out(&self) -> &NameServer<dyn AnalogOut> {
        &self.analog_out
    }

    /// Digital inputs by name.
    pub fn digital_in(&self) -> &NameServer<dyn DigitalIn> {
        &self.digital_in
    }

    /// Digital outputs by name.
    pub fn digital_out(&self) -> &NameServer<dyn DigitalOut> {
        &self.digital_out
    }

    /// Encoders by name.
    pub fn encoder(&self) -> &NameServer<dyn Encoder> {
        &self.encoder
    }

    /// Logical sensors by name.
    pub fn sensor(&self) -> &NameServer<dyn Sensor<f64>> {
        &self.sensor
    }

    /// Logical drives by name.
    pub fn drive(&self) -> &NameServer<dyn Drive> {
        &self.drive
    }

    /// Logical axes by name.
    pub fn axis(&self) -> &NameServer<dyn Axis> {
        &self.axis
    }
}

/// A device interface the registry serves, found by its type: code generic over the five
/// interfaces (a component's required devices) gets the right name server with
/// `<dyn AnalogIn as Served>::server(&registry)`.
pub trait Served: crate::Device + 'static {
    /// The interface.
    const INTERFACE: Interface;
    /// Its name server in `registry`.
    fn server(registry: &Registry) -> &NameServer<Self>;
}

macro_rules! served {
    ($($t:ident => $f:ident),+) => {$(
        impl Served for dyn $t {
            const INTERFACE: Interface = Interface::$t;
            fn server(registry: &Registry) -> &NameServer<Self> {
                registry.$f()
            }
        }
    )+};
}
served!(AnalogIn => analog_in, AnalogOut => analog_out, DigitalIn => digital_in, DigitalOut => digital_out, Encoder => encoder, Drive => drive, Axis => axis);

impl Served for dyn Sensor<f64> {
    const INTERFACE: Interface = Interface::Sensor;
    fn server(registry: &Registry) -> &NameServer<Self> {
        registry.sensor()
    }
}

impl Registry {
    /// Registers every device of card `name` under `name` (encoders and drives as
    /// `name.suffix`),
    /// owned by `name`. All or nothing: on error, what this call registered is removed again
    /// and a name held by someone else stays theirs.
    pub fn register_card(&self, name: &str, devices: CardDevices) -> Result<(), RegistryError> {
        let mut done: Vec<(Interface, String)> = Vec::new();
        let result = (|| {
            if let Some(d) = devices.analog_in {
                self.analog_in.register(name, name, d)?;
                done.push((Interface::AnalogIn, name.to_string()));
            }
            if let Some(d) = devices.analog_out {
                self.analog_out.register(name, name, d)?;
                done.push((Interface::AnalogOut, name.to_string()));
            }
            if let Some(d) = devices.digital_in {
                self.digital_in.register(name, name, d)?;
                done.push((Interface::DigitalIn, name.to_string()));
            }
            if let Some(d) = devices.digital_out {
                self.digital_out.register(name, name, d)?;
                done.push((Interface::DigitalOut, name.to_string()));
            }
            for (suffix, d) in devices.encoders {
                let full = format!("{name}.{suffix}");
                self.encoder.register(&full, name, d)?;
                done.push((Interface::Encoder, full));
            }
            for (suffix, d) in devices.drives {
                let full = format!("{name}.{suffix}");
                self.drive.register(&full, name, d)?;
                done.push((Interface::Drive, full));
            }
            Ok(())
        })();
        if result.is_err() {
            for (interface, n) in done {
                let _ = self.unregister(interface, &n);
            }
        }
        result
    }

    /// Removes `name` (and the aliases of it) from `interface`'s name server (see
    /// [`NameServer::unregister`]).
    pub fn unregister(
        &self,
        interface: Interface,
        name: &str,
    ) -> Result<Vec<String>, RegistryError> {
        match interface {
            Interface::AnalogIn => self.analog_in.unregister(name),
            Interface::AnalogOut => self.analog_out.unregister(name),
            Interface::DigitalIn => self.digital_in.unregister(name),
            Interface::DigitalOut => self.digital_out.unregister(name),
            Interface::Encoder => self.encoder.unregister(name),
            Interface::Sensor => self.sensor.unregister(name),
            Interface::Drive => self.drive.unregister(name),
            Interface::Axis => self.axis.unregister(name),
        }
    }

    /// Removes everything `owner` registered under every interface (a card going away).
    /// Returns what was removed.
    pub fn unregister_owner(&self, owner: &str) -> Vec<(Interface, String)> {
        let mut out = Vec::new();
        let mut take = |i: Interface, names: Vec<String>| {
            out.extend(names.into_iter().map(|n| (i, n)));
        };
        take(Interface::AnalogIn, self.analog_in.unregister_owner(owner));
        take(
            Interface::AnalogOut,
            self.analog_out.unregister_owner(owner),
        );
        take(
            Interface::DigitalIn,
            self.digital_in.unregister_owner(owner),
        );
        take(
            Interface::DigitalOut,
            self.digital_out.unregister_owner(owner),
        );
        take(Interface::Encoder, self.encoder.unregister_owner(owner));
        take(Interface::Sensor, self.sensor.unregister_owner(owner));
        take(Interface::Drive, self.drive.unregister_owner(owner));
        take(Interface::Axis, self.axis.unregister_owner(owner));
        out
    }

    /// Makes `alias` another name, under `interface`, for the device registered there as
    /// `target` (see [`NameServer::alias`]).
    pub fn alias(
        &self,
        interface: Interface,
        alias: &str,
        target: &str,
    ) -> Result<(), RegistryError> {
        match interface {
            Interface::AnalogIn => self.analog_in.alias(alias, target),
            Interface::AnalogOut => self.analog_out.alias(alias, target),
            Interface::DigitalIn => self.digital_in.alias(alias, target),
            Interface::DigitalOut => self.digital_out.alias(alias, target),
            Interface::Encoder => self.encoder.alias(alias, target),
            Interface::Sensor => self.sensor.alias(alias, target),
            Interface::Drive => self.drive.alias(alias, target),
            Interface::Axis => self.axis.alias(alias, target),
        }
    }

    /// The health of the device named `name` under `interface`, if there is one.
    pub fn health(&self, interface: Interface, name: &str) -> Option<crate::Health> {
        match interface {
            Interface::AnalogIn => self.analog_in.get(name).map(|d| d.health()),
            Interface::AnalogOut => self.analog_out.get(name).map(|d| d.health()),
            Interface::DigitalIn => self.digital_in.get(name).map(|d| d.health()),
            Interface::DigitalOut => self.digital_out.get(name).map(|d| d.health()),
            Interface::Encoder => self.encoder.get(name).map(|d| d.health()),
            Interface::Sensor => self.sensor.get(name).map(|d| d.health()),
            Interface::Drive => self.drive.get(name).map(|d| d.health()),
            Interface::Axis => self.axis.get(name).map(|d| d.health()),
        }
    }

    /// Every name under every interface, by interface then name.
    pub fn entries(&self) -> Vec<RegistryEntry> {
        let per = [
            (Interface::AnalogIn, self.analog_in.names()),
            (Interface::AnalogOut, self.analog_out.names()),
            (Interface::DigitalIn, self.digital_in.names()),
            (Interface::DigitalOut, self.digital_out.names()),
            (Interface::Encoder, self.encoder.names()),
            (Interface::Sensor, self.sensor.names()),
            (Interface::Drive, self.drive.names()),
            (Interface::Axis, self.axis.names()),
        ];
        per.into_iter()
            .flat_map(|(interface, names)| {
                names
                    .into_iter()
                    .map(move |info| RegistryEntry { interface, info })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn server() -> NameServer<str> {
        NameServer::new(Interface::DigitalOut)
    }

    fn dev(s: &str) -> Arc<str> {
        Arc::from(s)
    }

    #[test]
    fn register_lookup_list() {
        let ns = server();
        ns.register("b", "card1", dev("B")).unwrap();
        ns.register("a", "card0", dev("A")).unwrap();
        assert_eq!(&*ns.lookup("a").unwrap(), "A");
        assert!(ns.get("c").is_none());
        let names: Vec<_> = ns.names().into_iter().map(|n| (n.name, n.owner)).collect();
        assert_eq!(
            names,
            vec![("a".into(), "card0".into()), ("b".into(), "card1".into())]
        );
    }

    #[test]
    fn duplicate_names_both_owners() {
        let ns = server();
        ns.register("io", "card0", dev("A")).unwrap();
        let e = ns.register("io", "card1", dev("B")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "DigitalOut name \"io\" is already registered by \"card0\"; \"card1\" cannot register it too"
        );
        assert_eq!(
            &*ns.lookup("io").unwrap(),
            "A",
            "the first registration stays"
        );
    }

    #[test]
    fn not_found_lists_what_exists() {
        let ns = server();
        ns.register("x", "c", dev("X")).unwrap();
        ns.register("y", "c", dev("Y")).unwrap();
        let e = ns.lookup("z").unwrap_err();
        assert_eq!(e.to_string(), "no DigitalOut named \"z\"; registered: x, y");
    }

    #[test]
    fn aliases() {
        let ns = server();
        ns.register("card.do", "card", dev("D")).unwrap();
        ns.alias("ThreadScope", "card.do").unwrap();
        ns.alias("scope2", "ThreadScope").unwrap();
        assert_eq!(&*ns.lookup("ThreadScope").unwrap(), "D");
        let info = ns.names().into_iter().find(|n| n.name == "scope2").unwrap();
        assert_eq!(
            info.alias_of.as_deref(),
            Some("card.do"),
            "alias of an alias names the original"
        );
        let e = ns.register("ThreadScope", "other", dev("O")).unwrap_err();
        assert!(e.to_string().contains("an alias of card.do"), "{e}");
        assert!(ns.alias("a", "missing").is_err());
        // Removing an alias keeps the target; removing the target takes its aliases.
        assert_eq!(ns.unregister("scope2").unwrap(), vec!["scope2"]);
        assert!(ns.contains("card.do"));
        assert_eq!(
            ns.unregister("card.do").unwrap(),
            vec!["ThreadScope", "card.do"]
        );
        assert!(ns.is_empty());
    }

    #[test]
    fn invalid_names() {
        let ns = server();
        for bad in ["", "two words", "tab\there", "nl\n"] {
            assert!(matches!(
                ns.register(bad, "c", dev("x")),
                Err(RegistryError::InvalidName { .. })
            ));
        }
        // Long hierarchical names are fine.
        let long = "plant/line-3/cell.7/".repeat(20);
        ns.register(&long, "c", dev("x")).unwrap();
    }

    #[test]
    fn unregister_owner_takes_aliases() {
        let ns = server();
        ns.register("a", "card0", dev("A")).unwrap();
        ns.register("b", "card1", dev("B")).unwrap();
        ns.alias("scope", "a").unwrap();
        assert_eq!(ns.unregister_owner("card0"), vec!["a", "scope"]);
        assert_eq!(ns.len(), 1);
        assert!(ns.unregister_owner("nobody").is_empty());
    }

    #[test]
    fn concurrent_lookups_while_registering() {
        let ns = Arc::new(server());
        ns.register("stable", "c", dev("S")).unwrap();
        let readers: Vec<_> = (0..2)
            .map(|_| {
                let ns = Arc::clone(&ns);
                std::thread::spawn(move || {
                    for _ in 0..20_000 {
                        assert_eq!(&*ns.lookup("stable").unwrap(), "S");
                    }
                })
            })
            .collect();
        for i in 0..500 {
            ns.register(&format!("n{i}"), "c", dev("N")).unwrap();
        }
        for r in readers {
            r.join().unwrap();
        }
        assert_eq!(ns.len(), 501);
    }
}
