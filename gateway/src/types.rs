//! Everything a deployment may name by type: component types and driver types.

use crate::components::ComponentTypes;
use crate::drivers::DriverTypes;

/// The component and driver types a deployment may use.
#[derive(Clone)]
pub struct Types {
    /// `type = "…"` of a `[[component]]`.
    pub components: ComponentTypes,
    /// `driver = "…"` of a `[[card]]`.
    pub drivers: DriverTypes,
}

impl Types {
    /// hwgw's own: the built-in component types and drivers.
    pub fn builtin() -> Self {
        Types {
            components: ComponentTypes::builtin(),
            drivers: DriverTypes::builtin(),
        }
    }
}
