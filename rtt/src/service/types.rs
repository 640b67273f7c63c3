//! What services are made of, as listed and as refused: [`Multiplicity`], the listings
//! [`ProvidedInfo`] and [`RequiredInfo`], and [`BindError`]; see [`super`].

use device_interface::RegistryError;
use serde::{Deserialize, Serialize};
use std::fmt;

/// How many devices a requirement takes: at least `min`, at most `max` (`None`: any).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Multiplicity {
    /// The fewest devices it works with.
    pub min: u32,
    /// The most it takes; `None` for no limit.
    pub max: Option<u32>,
}

impl Multiplicity {
    /// Exactly one.
    pub const ONE: Multiplicity = Multiplicity {
        min: 1,
        max: Some(1),
    };
    /// Any number, none included (`*`).
    pub const ANY: Multiplicity = Multiplicity { min: 0, max: None };

    /// Whether `n` devices fit.
    pub fn admits(&self, n: usize) -> bool {
        n >= self.min as usize && self.max.is_none_or(|m| n <= m as usize)
    }
}

/// Why a multiplicity was not understood.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "multiplicity {given:?}: expected \"one\", a count (\"2\"), a range (\"0..2\", \"1..*\") or \"*\""
)]
pub struct MultiplicityError {
    /// What was given.
    pub given: String,
}

impl std::str::FromStr for Multiplicity {
    type Err = MultiplicityError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let err = || MultiplicityError {
            given: s.to_string(),
        };
        let bound = |t: &str| t.trim().parse::<u32>().map_err(|_| err());
        let t = s.trim();
        match t {
            "one" => return Ok(Multiplicity::ONE),
            "*" => return Ok(Multiplicity::ANY),
            _ => {}
        }
        let m = match t.split_once("..") {
            None => {
                let n = bound(t)?;
                Multiplicity {
                    min: n,
                    max: Some(n),
                }
            }
            Some((lo, "*")) => Multiplicity {
                min: bound(lo)?,
                max: None,
            },
            Some((lo, hi)) => Multiplicity {
                min: bound(lo)?,
                max: Some(bound(hi)?),
            },
        };
        if m.max.is_some_and(|hi| hi < m.min) {
            return Err(err());
        }
        Ok(m)
    }
}

impl fmt::Display for Multiplicity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.min, self.max) {
            (1, Some(1)) => f.write_str("one"),
            (0, None) => f.write_str("*"),
            (lo, None) => write!(f, "{lo}..*"),
            (lo, Some(hi)) if lo == hi => write!(f, "{lo}"),
            (lo, Some(hi)) => write!(f, "{lo}..{hi}"),
        }
    }
}

/// A service a component provides, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProvidedInfo {
    /// The service's name (`camera`).
    pub name: String,
    /// Its operations, without the service's prefix.
    pub operations: Vec<String>,
    /// Its ports, without the service's prefix.
    pub ports: Vec<String>,
}

/// What a requirement asks for.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum RequiredKind {
    /// A service: operations by name and type.
    Service {
        /// Each operation with its type in the control protocol's names
        /// (`set_resolution(u32, u32) -> bool`).
        operations: Vec<String>,
    },
    /// Devices of one interface.
    Devices {
        /// The interface (`DigitalOut`).
        interface: String,
        /// How many (`one`, `0..2`, `*`).
        multiplicity: String,
    },
}

/// A service or devices a component requires, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RequiredInfo {
    /// The requirement's name (`camera`, `valves`).
    pub name: String,
    /// What it asks for.
    #[serde(flatten)]
    pub kind: RequiredKind,
    /// The component configures and starts without it.
    pub optional: bool,
    /// What it is bound to: `component.service`, or device names; empty when unbound.
    pub bound_to: Vec<String>,
    /// Bound, and the provider Running (devices: every one online).
    pub ready: bool,
    /// Times it stopped being ready while the component ran.
    pub lost: u64,
    /// Times it was ready again.
    pub back: u64,
}

/// Why a binding was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BindError {
    /// The component requires nothing by that name.
    #[error("{component:?} requires no {name:?}; it requires: {}", if .known.is_empty() { "nothing".to_string() } else { .known.join(", ") })]
    UnknownRequirement {
        /// The requiring component.
        component: String,
        /// The name asked for.
        name: String,
        /// What it does require.
        known: Vec<String>,
    },
    /// A service requirement given devices, or a device requirement given a service.
    #[error("{component:?} requires {name:?} as {expected}, not as {given}")]
    WrongKind {
        /// The requiring component.
        component: String,
        /// The requirement.
        name: String,
        /// What it is (`a service`, `DigitalOut devices`).
        expected: String,
        /// What the binding gave.
        given: &'static str,
    },
    /// The provider offers no service by that name.
    #[error("{provider:?} provides no service {service:?}; it provides: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NotProvided {
        /// The provider.
        provider: String,
        /// The service asked for.
        service: String,
        /// What it does provide.
        known: Vec<String>,
    },
    /// A required operation the provided service lacks.
    #[error("{at} does not exist, and {:?} requires it as {required}", at.component)]
    MissingOperation {
        /// Where it was looked for.
        at: Box<OperationAt>,
        /// Its required type.
        required: String,
    },
    /// A provided operation of another type than required.
    #[error("{at} is {provided}, but {:?} requires {required}", at.component)]
    WrongType {
        /// Where it was found.
        at: Box<OperationAt>,
        /// Its type as provided.
        provided: String,
        /// Its type as required.
        required: String,
    },
    /// A device that is not registered under the interface.
    #[error("{component:?} requires {name:?}: {source}")]
    Device {
        /// The requiring component.
        component: String,
        /// The requirement.
        name: String,
        /// The registry's answer.
        source: Box<RegistryError>,
    },
    /// One device named twice.
    #[error("{component:?} requires {name:?}: device {device:?} is named twice")]
    DuplicateDevice {
        /// The requiring component.
        component: String,
        /// The requirement.
        name: String,
        /// The device.
        device: String,
    },
    /// Too few or too many devices.
    #[error("{component:?} requires {multiplicity} {interface} devices as {name:?}; {given} given")]
    Multiplicity {
        /// The requiring component.
        component: String,
        /// The requirement.
        name: String,
        /// The interface.
        interface: String,
        /// How many it takes.
        multiplicity: Multiplicity,
        /// How many were given.
        given: usize,
    },
}

/// A required operation's place in a provider: `provider.service.operation`, for the
/// requiring `component`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OperationAt {
    /// The requiring component.
    pub component: String,
    /// The provider.
    pub provider: String,
    /// The service.
    pub service: String,
    /// The operation.
    pub operation: String,
}

impl fmt::Display for OperationAt {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{}.{}", self.provider, self.service, self.operation)
    }
}

#[cfg(test)]
mod tests {
    use super::Multiplicity;

    #[test]
    fn multiplicities() {
        let m = |s: &str| s.parse::<Multiplicity>();
        assert_eq!(m("one"), Ok(Multiplicity::ONE));
        assert_eq!(m("1"), Ok(Multiplicity::ONE));
        assert_eq!(m("*"), Ok(Multiplicity::ANY));
        assert_eq!(
            m("0..2"),
            Ok(Multiplicity {
                min: 0,
                max: Some(2)
            })
        );
        assert_eq!(m("1..*"), Ok(Multiplicity { min: 1, max: None }));
        for bad in ["", "two", "2..1", "..", "-1", "1..x"] {
            assert!(m(bad).is_err(), "{bad:?}");
        }
        for s in ["one", "*", "0..2", "1..*", "3"] {
            assert_eq!(m(s).map(|x| x.to_string()).as_deref(), Ok(s));
        }
        assert!(Multiplicity::ANY.admits(0) && !Multiplicity::ONE.admits(2));
    }
}
