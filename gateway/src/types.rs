//! Everything a deployment may name by type: component types, driver types and server
//! types.

use crate::components::ComponentTypes;
use crate::drivers::DriverTypes;
use crate::servers::ServerTypes;

/// The component, driver and server types a deployment may use.
#[derive(Clone)]
pub struct Types {
    /// `type = "…"` of a `[[component]]`.
    pub components: ComponentTypes,
    /// `driver = "…"` of a `[[card]]`.
    pub drivers: DriverTypes,
    /// The top-level server sections (`[modbus_server]`).
    pub servers: ServerTypes,
}

impl Types {
    /// hwgw's own: the built-in component types, drivers and server types.
    pub fn builtin() -> Self {
        Types {
            components: ComponentTypes::builtin(),
            drivers: DriverTypes::builtin(),
            servers: ServerTypes::builtin(),
        }
    }
}
