//! SMBus transfers to one chip, the only kind every adapter and the kernel's i2c-stub
//! answer: byte-data and word-data reads and writes to a register. [`LinuxChip`] speaks
//! them through i2c-dev (`i2cdev`); tests may give a chip model anything else that does.

use i2cdev::core::I2CDevice;
use i2cdev::linux::{LinuxI2CDevice, LinuxI2CError};
use std::path::Path;

/// A failed transfer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Transfer {
    /// Nothing answered at the address (a NAK: `ENXIO`, `EREMOTEIO`, or `ENODEV` from
    /// i2c-stub), or the adapter went away.
    #[error("no answer at the chip's address ({0})")]
    NoAnswer(String),
    /// The adapter reported another error (a timeout, lost arbitration, a busy bus).
    #[error("transfer failed: {0}")]
    Failed(String),
}

/// Register transfers to one chip.
pub trait Smbus: Send {
    /// Reads byte register `reg`.
    fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer>;
    /// Writes byte register `reg`.
    fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer>;
    /// Reads word register `reg` (SMBus order: the low byte first on the wire).
    fn read_word(&mut self, reg: u8) -> Result<u16, Transfer>;
    /// Writes word register `reg` (SMBus order: the low byte first on the wire).
    fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer>;
}

/// One chip of an i2c-dev bus.
pub struct LinuxChip(LinuxI2CDevice);

fn transfer(e: LinuxI2CError) -> Transfer {
    match e {
        LinuxI2CError::Errno(n) if [libc_enxio(), libc_eremoteio(), libc_enodev()].contains(&n) => {
            Transfer::NoAnswer(std::io::Error::from_raw_os_error(n).to_string())
        }
        LinuxI2CError::Errno(n) => {
            Transfer::Failed(std::io::Error::from_raw_os_error(n).to_string())
        }
        LinuxI2CError::Io(e) => Transfer::Failed(e.to_string()),
    }
}

// The errno values (Linux, every architecture hwgw builds for).
const fn libc_enxio() -> i32 {
    6
}
const fn libc_enodev() -> i32 {
    19
}
const fn libc_eremoteio() -> i32 {
    121
}

impl LinuxChip {
    /// Opens the bus at `path` for the chip at `address`. Fails when a kernel driver has
    /// claimed that address (`EBUSY`: hwgw does not take a chip from the kernel).
    pub fn open(path: &Path, address: u16) -> Result<LinuxChip, String> {
        LinuxI2CDevice::new(path, address)
            .map(LinuxChip)
            .map_err(|e| match e {
                LinuxI2CError::Errno(16) => format!(
                    "{}: address {address:#04x} is claimed by a kernel driver (EBUSY)",
                    path.display()
                ),
                e => format!("{}: address {address:#04x}: {e}", path.display()),
            })
    }
}

impl Smbus for LinuxChip {
    fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer> {
        self.0.smbus_read_byte_data(reg).map_err(transfer)
    }
    fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer> {
        self.0.smbus_write_byte_data(reg, value).map_err(transfer)
    }
    fn read_word(&mut self, reg: u8) -> Result<u16, Transfer> {
        self.0.smbus_read_word_data(reg).map_err(transfer)
    }
    fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer> {
        self.0.smbus_write_word_data(reg, value).map_err(transfer)
    }
}
