//! comedi boards in the kernel rig's guest ([`crate::rig::comedi`]): `comedi_test` (eight
//! analog outputs whose last value each analog input of the same channel reads back) and
//! `comedi_parport` on the rig's emulated parallel port, attached to and detached from
//! their legacy device files with comedilib's `comedi_config`; and the parallel port's
//! register writes as qemu recorded them, outside the guest's kernel — the independent
//! read-back of the port's outputs.

use crate::run;
use std::io;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A board attached to a comedi device file; detached when dropped.
#[derive(Debug)]
pub struct ComediBoard {
    path: PathBuf,
    driver: String,
    options: String,
}

impl ComediBoard {
    /// comedi_test on `path` (AI subdevice 0 and AO subdevice 1, 8 channels each, 16 bit,
    /// ±10 V and ±5 V), with the waveform options comedi_config takes for it.
    pub fn comedi_test(path: &str) -> io::Result<ComediBoard> {
        Self::attach(path, "comedi_test", "1000000,100000")
    }

    /// comedi_parport on `path`, driving the rig's parallel port at 0x378: subdevice 0
    /// the 8 data lines (DIO, one direction for all), 1 the 5 status lines (DI), 2 the 4
    /// control lines (DO).
    pub fn parport(path: &str) -> io::Result<ComediBoard> {
        Self::attach(path, "comedi_parport", "0x378")
    }

    fn attach(path: &str, driver: &str, options: &str) -> io::Result<ComediBoard> {
        let board = ComediBoard {
            path: PathBuf::from(path),
            driver: driver.into(),
            options: options.into(),
        };
        board.configure()?;
        Ok(board)
    }

    /// Its device file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Detaches the board (`comedi_config -r`): the device file stays, unconfigured.
    pub fn remove(&self) -> io::Result<()> {
        run("comedi_config", &["-r", &self.path.to_string_lossy()]).map(|_| ())
    }

    /// Attaches it again, as at first.
    pub fn configure(&self) -> io::Result<()> {
        run(
            "comedi_config",
            &[&self.path.to_string_lossy(), &self.driver, &self.options],
        )
        .map(|_| ())
    }
}

impl Drop for ComediBoard {
    fn drop(&mut self) {
        let _ = self.remove();
    }
}

/// A write to the parallel port's data register, as qemu traced it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PortWrite {
    /// When, in µs of the host's wall clock.
    pub at_us: u64,
    /// The byte written.
    pub value: u8,
}

/// The parallel port's register writes qemu records in the run directory
/// ([`kernel_rig::Rig::parallel_port`]).
#[derive(Debug, Clone)]
pub struct PortTrace {
    path: PathBuf,
}

impl PortTrace {
    /// The trace of this run (in the guest).
    pub fn open() -> io::Result<PortTrace> {
        let run = kernel_rig::run_dir().ok_or_else(|| {
            io::Error::other(format!(
                "{} is not set: not in the rig's guest",
                kernel_rig::RUN_ENV
            ))
        })?;
        Ok(PortTrace {
            path: run.join(kernel_rig::PARPORT_TRACE),
        })
    }

    /// Every write to the data register so far, in order. A line reads
    /// `PID@SECONDS.MICROS:parallel_ioport_write write [DATA] addr 0x00 val 0x55`.
    pub fn data_writes(&self) -> io::Result<Vec<PortWrite>> {
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(e),
        };
        let mut out = Vec::new();
        for line in text.lines() {
            let Some((stamp, event)) = line.split_once(":parallel_ioport_write ") else {
                continue;
            };
            if !event.contains("addr 0x00 ") {
                continue;
            }
            let bad = || io::Error::other(format!("{}: cannot read {line:?}", self.path.display()));
            let value = event.rsplit_once("val 0x").ok_or_else(bad)?.1;
            let value = u8::from_str_radix(value.trim(), 16).map_err(|_| bad())?;
            let stamp = stamp.split_once('@').ok_or_else(bad)?.1;
            let (s, us) = stamp.split_once('.').ok_or_else(bad)?;
            let at_us = s.parse::<u64>().map_err(|_| bad())? * 1_000_000
                + us.parse::<u64>().map_err(|_| bad())?;
            out.push(PortWrite { at_us, value });
        }
        Ok(out)
    }

    /// The data register as last written, if ever.
    pub fn data(&self) -> io::Result<Option<u8>> {
        Ok(self.data_writes()?.last().map(|w| w.value))
    }

    /// Waits up to `patience` for the data register's last write to be `value`.
    pub fn wait_data(&self, value: u8, patience: Duration) -> io::Result<()> {
        let deadline = Instant::now() + patience;
        loop {
            let now = self.data()?;
            if now == Some(value) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(io::Error::other(format!(
                    "the parallel port's data register is {now:02x?}, not {value:#04x}, after {patience:?}"
                )));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}
