//! The [`Server`] trait: something the gateway serves beside its cards (hwgw as a Modbus
//! TCP server over chosen devices), built over the registry with the deployment, started
//! with the gateway, stopped first at stop so no client write races the safe values.

/// A server of a deployment.
pub trait Server: Send + Sync {
    /// Its deployment key, e.g. `modbus_server`.
    fn name(&self) -> &str;

    /// Starts serving; returns where it listens.
    fn start(&self) -> Result<String, String>;

    /// Stops serving (closing its clients' connections) and waits for that; idempotent.
    fn stop(&self);

    /// Where it listens while running.
    fn address(&self) -> Option<String>;

    /// Its state and counters for `hwgw status` (as a card's: where, and a snapshot).
    /// Default: none.
    fn status(&self) -> Option<crate::CardStatus> {
        None
    }

    /// `Ok` while it serves as it should (part of the gateway's health, which feeds the
    /// systemd watchdog); else what is wrong. Default: `Ok`.
    fn health(&self) -> Result<(), String> {
        Ok(())
    }
}
