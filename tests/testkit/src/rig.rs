//! Kernel rig presets for the tests that need a kernel bus.

use crate::peers::{CAN_UTILS, I2C_TOOLS, Peer, Probe, require};
use kernel_rig::Rig;

/// `rig` with `peer` installed on the host before it boots (the guest runs the host's
/// files, so the guest has it too).
pub fn with_peer(rig: Rig, peer: &Peer) -> Rig {
    match peer.probe {
        Probe::Command(command) => peer
            .packages
            .iter()
            .fold(rig, |rig, package| rig.tool(command, package)),
        Probe::Python(_) | Probe::Files(_) => {
            // Installed now, on the host (in the guest this only checks); a test that
            // still lacks it fails on its own `ensure` with the same message.
            if let Err(e) = require(peer) {
                eprintln!("{e}");
            }
            rig
        }
    }
}

/// A guest with vcan and CAN_RAW loaded and can-utils on the host (the CAN tests' rig).
pub fn vcan() -> Rig {
    with_peer(Rig::new().module("vcan").module("can_raw"), &CAN_UTILS)
}

/// A guest with i2c-dev loaded and i2c-tools on the host (the I2C tests' rig); each test
/// loads i2c-stub with the chip addresses it wants ([`crate::i2cstub::I2cStub`]).
pub fn i2c_stub() -> Rig {
    with_peer(Rig::new().module("i2c-dev"), &I2C_TOOLS)
}

/// The comedi tests' rig ([`Rig::comedi`]): comedi_test and comedi_parport ready, the
/// parallel port's writes recorded by qemu; each test attaches the boards it wants
/// ([`crate::comedi`]).
pub fn comedi() -> Rig {
    Rig::new().comedi()
}
