//! What is listed about a port: its direction, data type and documentation.

use serde::Serialize;
use serde::de::DeserializeOwned;
use std::fmt;

/// Data direction of a port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// An input port.
    Input,
    /// An output port.
    Output,
}

impl fmt::Display for Direction {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Direction::Input => "input",
            Direction::Output => "output",
        })
    }
}

/// What a port can carry: clonable, sendable, serde (for the dynamic interface).
pub trait PortData: Clone + Send + Sync + Serialize + DeserializeOwned + 'static {}
impl<T: Clone + Send + Sync + Serialize + DeserializeOwned + 'static> PortData for T {}

/// A value of a port that has a name (a DBC value description: gear 3 is "D"): shown when
/// the port is described, and accepted in its place when the port is written through the
/// dynamic layer (`hwgw set … D`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct NamedValue {
    /// The name.
    pub name: String,
    /// The value it stands for, as the port carries it.
    pub value: serde_json::Value,
}

/// A port, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct PortInfo {
    /// Name.
    pub name: String,
    /// What it carries.
    pub doc: String,
    /// Direction.
    pub direction: Direction,
    /// Type of the data, as the control protocol names it ([`crate::typename`]).
    pub type_name: String,
    /// True for an input port that wakes its component.
    pub event: bool,
    /// Its values that have names.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub values: Vec<NamedValue>,
}
