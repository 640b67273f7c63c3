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

/// A port, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct PortInfo {
    /// Name.
    pub name: String,
    /// What it carries.
    pub doc: String,
    /// Direction.
    pub direction: Direction,
    /// Rust type of the data.
    pub type_name: String,
    /// True for an input port that wakes its component.
    pub event: bool,
}
