//! The kernel's I2C/SMBus stub (`i2c-stub`) as a bus of register-based chips, for tests in
//! the kernel rig's guest ([`crate::rig::i2c_stub`]): loaded with the chip addresses a
//! test wants, found as `/dev/i2c-N` by its adapter's name, and read and written from
//! outside with i2c-tools (`i2cget`, `i2cset`), the independent peer.

use crate::run;
use std::io;
use std::path::{Path, PathBuf};

/// The name the stub's adapter has in `/sys/class/i2c-dev/*/name`.
pub const ADAPTER_NAME: &str = "SMBus stub driver";

/// An i2c-stub bus with chips at some addresses; unloaded when dropped.
#[derive(Debug)]
pub struct I2cStub {
    /// The adapter's number (`/dev/i2c-<bus>`).
    pub bus: u32,
}

fn parse(text: &str) -> io::Result<u16> {
    u16::from_str_radix(text.trim_start_matches("0x"), 16)
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, format!("{text:?}: {e}")))
}

impl I2cStub {
    /// (Re)loads i2c-stub with chips at `addresses` (at most 10, as the module takes).
    /// Fails while a process holds the stub's `/dev/i2c-N` open: the open file pins the
    /// module, so chips cannot come and go under a running reader.
    pub fn load(addresses: &[u8]) -> io::Result<I2cStub> {
        let loaded = Path::new("/sys/module/i2c_stub").exists();
        if loaded {
            run("modprobe", &["-r", "i2c-stub"])?;
        }
        let list: Vec<String> = addresses.iter().map(|a| format!("{a:#04x}")).collect();
        run(
            "modprobe",
            &["i2c-stub", &format!("chip_addr={}", list.join(","))],
        )?;
        Ok(I2cStub { bus: Self::find()? })
    }

    fn find() -> io::Result<u32> {
        for entry in std::fs::read_dir("/sys/class/i2c-dev")? {
            let dir = entry?.path();
            let name = std::fs::read_to_string(dir.join("name")).unwrap_or_default();
            if name.trim() == ADAPTER_NAME
                && let Some(n) = dir
                    .file_name()
                    .and_then(|n| n.to_str())
                    .and_then(|n| n.strip_prefix("i2c-"))
                    .and_then(|n| n.parse().ok())
            {
                return Ok(n);
            }
        }
        Err(io::Error::new(
            io::ErrorKind::NotFound,
            format!("no /sys/class/i2c-dev/*/name is {ADAPTER_NAME:?} (is i2c-dev loaded?)"),
        ))
    }

    /// The adapter's character device.
    pub fn path(&self) -> PathBuf {
        Path::new("/dev").join(format!("i2c-{}", self.bus))
    }

    /// Sets byte register `reg` of the chip at `addr` (`i2cset`).
    pub fn set_byte(&self, addr: u8, reg: u8, value: u8) -> io::Result<()> {
        self.i2cset(addr, reg, &format!("{value:#04x}"), "b")
    }

    /// Sets word register `reg` of the chip at `addr` as SMBus sends it (low byte first).
    pub fn set_word(&self, addr: u8, reg: u8, value: u16) -> io::Result<()> {
        self.i2cset(addr, reg, &format!("{value:#06x}"), "w")
    }

    fn i2cset(&self, addr: u8, reg: u8, value: &str, mode: &str) -> io::Result<()> {
        run(
            "i2cset",
            &[
                "-y",
                &self.bus.to_string(),
                &format!("{addr:#04x}"),
                &format!("{reg:#04x}"),
                value,
                mode,
            ],
        )
        .map(|_| ())
    }

    /// Byte register `reg` of the chip at `addr` (`i2cget`).
    pub fn get_byte(&self, addr: u8, reg: u8) -> io::Result<u8> {
        Ok(self.i2cget(addr, reg, "b")? as u8)
    }

    /// Word register `reg` of the chip at `addr` as SMBus reads it (low byte first).
    pub fn get_word(&self, addr: u8, reg: u8) -> io::Result<u16> {
        self.i2cget(addr, reg, "w")
    }

    fn i2cget(&self, addr: u8, reg: u8, mode: &str) -> io::Result<u16> {
        parse(&run(
            "i2cget",
            &[
                "-y",
                &self.bus.to_string(),
                &format!("{addr:#04x}"),
                &format!("{reg:#04x}"),
                mode,
            ],
        )?)
    }
}

impl Drop for I2cStub {
    fn drop(&mut self) {
        let _ = run("modprobe", &["-r", "i2c-stub"]);
    }
}
