//! SMBus transfers to one chip, the only kind every adapter and the kernel's i2c-stub
//! answer: byte-data and word-data reads and writes to a register. [`LinuxChip`] speaks
//! them through i2c-dev (`i2cdev`); tests may give a chip model anything else that does.
//! [`find_bus`] finds a bus's character device by its path or its adapter's name.

use i2cdev::core::I2CDevice;
use i2cdev::linux::{LinuxI2CDevice, LinuxI2CError};
use std::path::{Path, PathBuf};

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

/// Why a bus, or a chip on it, could not be opened.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OpenError {
    /// The bus named is not there, or is no I2C bus: what there is instead.
    #[error("{0}")]
    NoBus(String),
    /// A kernel driver has claimed the chip's address (hwgw does not take a chip from
    /// the kernel).
    #[error("{path}: address {address:#04x} is claimed by a kernel driver (EBUSY)")]
    Claimed {
        /// The bus.
        path: String,
        /// The chip's address.
        address: u16,
    },
    /// Opening the bus for the chip failed otherwise.
    #[error("{path}: address {address:#04x}: {why}")]
    Failed {
        /// The bus.
        path: String,
        /// The chip's address.
        address: u16,
        /// The OS error.
        why: String,
    },
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
    pub fn open(path: &Path, address: u16) -> Result<LinuxChip, OpenError> {
        let path_text = || path.display().to_string();
        LinuxI2CDevice::new(path, address)
            .map(LinuxChip)
            .map_err(|e| match e {
                LinuxI2CError::Errno(16) => OpenError::Claimed {
                    path: path_text(),
                    address,
                },
                e => OpenError::Failed {
                    path: path_text(),
                    address,
                    why: e.to_string(),
                },
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

/// The adapters an error lists at most.
const LISTED: usize = 16;

/// The major number of i2c-dev's character devices (`/dev/i2c-N`).
pub const I2C_DEV_MAJOR: u64 = 89;

/// The bus `spec` names: a path (anything with a `/`), which must lead to an i2c-dev
/// character device (major [`I2C_DEV_MAJOR`]; checked from `stat`, nothing opened), else
/// an adapter's name.
pub fn find_bus(spec: &str) -> Result<PathBuf, OpenError> {
    if spec.contains('/') {
        let path = Path::new(spec);
        return match driver_api::node::Node::of(path) {
            Ok(driver_api::node::Node::Char {
                major: I2C_DEV_MAJOR,
                ..
            }) => Ok(path.to_path_buf()),
            Ok(other) => Err(OpenError::NoBus(format!(
                "{spec} is not an I2C bus: it is {other}; an i2c-dev bus is a character \
                 device of major {I2C_DEV_MAJOR} (/dev/i2c-N)"
            ))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(OpenError::NoBus(format!(
                "{spec}: no such I2C bus (is i2c-dev loaded?)"
            ))),
            Err(e) => Err(OpenError::NoBus(format!("{spec}: {e}"))),
        };
    }
    let mut adapters = Vec::new();
    if let Ok(dir) = std::fs::read_dir("/sys/class/i2c-dev") {
        for entry in dir.flatten() {
            let dev = entry.file_name().to_string_lossy().to_string();
            let name = std::fs::read_to_string(entry.path().join("name")).unwrap_or_default();
            adapters.push((dev, name.trim().to_string()));
        }
    }
    adapters.sort();
    let found: Vec<&(String, String)> = adapters.iter().filter(|(_, n)| n == spec).collect();
    match found.as_slice() {
        [(dev, _)] => Ok(Path::new("/dev").join(dev)),
        [] if adapters.is_empty() => Err(OpenError::NoBus(format!(
            "no I2C adapter is named {spec:?}; there are none (is i2c-dev loaded?)"
        ))),
        [] => Err(OpenError::NoBus(format!(
            "no I2C adapter is named {spec:?}; the adapters are {}",
            adapters
                .iter()
                .take(LISTED)
                .map(|(d, n)| format!("{d} ({n})"))
                .collect::<Vec<_>>()
                .join(", ")
        ))),
        many => Err(OpenError::NoBus(format!(
            "{} adapters are named {spec:?} ({}); give the path",
            many.len(),
            many.iter()
                .map(|(d, _)| d.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

/// A chip for unit tests: i2c-stub's model (one word per register, byte transfers on its
/// low byte), every transfer logged.
#[cfg(test)]
pub(crate) mod fake {
    use super::{Smbus, Transfer};
    use std::sync::{Arc, Mutex, PoisonError};

    /// What the test and the chip model share.
    #[derive(Default)]
    pub struct State {
        pub words: Vec<u16>,
        /// Each write: (register, value).
        pub writes: Vec<(u8, u16)>,
    }

    /// The chip.
    #[derive(Clone)]
    pub struct Registers(pub Arc<Mutex<State>>);

    impl Registers {
        pub fn new() -> Registers {
            Registers(Arc::new(Mutex::new(State {
                words: vec![0; 256],
                writes: Vec::new(),
            })))
        }

        pub fn state(&self) -> std::sync::MutexGuard<'_, State> {
            self.0.lock().unwrap_or_else(PoisonError::into_inner)
        }

        pub fn set(&self, reg: u8, value: u16) {
            self.state().words[reg as usize] = value;
        }

        pub fn get(&self, reg: u8) -> u16 {
            self.state().words[reg as usize]
        }

        /// The writes so far, taken.
        pub fn writes(&self) -> Vec<(u8, u16)> {
            std::mem::take(&mut self.state().writes)
        }
    }

    impl Smbus for Registers {
        fn read_byte(&mut self, reg: u8) -> Result<u8, Transfer> {
            Ok(self.get(reg) as u8)
        }
        fn write_byte(&mut self, reg: u8, value: u8) -> Result<(), Transfer> {
            let mut s = self.state();
            let w = &mut s.words[reg as usize];
            *w = (*w & 0xff00) | u16::from(value);
            s.writes.push((reg, u16::from(value)));
            Ok(())
        }
        fn read_word(&mut self, reg: u8) -> Result<u16, Transfer> {
            Ok(self.get(reg))
        }
        fn write_word(&mut self, reg: u8, value: u16) -> Result<(), Transfer> {
            let mut s = self.state();
            s.words[reg as usize] = value;
            s.writes.push((reg, value));
            Ok(())
        }
    }
}
