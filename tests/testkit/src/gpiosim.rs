//! Chips of the kernel's GPIO simulator (gpio-sim, configured through configfs), for tests
//! in the kernel rig's guest ([`kernel_rig::Rig::gpio_sim`]): made live with named lines,
//! inputs driven from outside by their simulated pull, outputs read back; and
//! [`GpioTrace`], the kernel's own record of every level driven on a line.

use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const CONFIGFS: &str = "/sys/kernel/config/gpio-sim";

/// A live gpio-sim chip of one bank; taken down when dropped.
#[derive(Debug)]
pub struct SimChip {
    dir: PathBuf,
    lines: u32,
    names: Vec<u32>,
    /// The platform device (`gpio-sim.0`).
    pub dev_name: String,
    /// The GPIO chip (`gpiochip1`): its character device is `/dev/<chip_name>`.
    pub chip_name: String,
    /// The chip's label (the `label` given).
    pub label: String,
}

fn write(path: &Path, value: &str) -> io::Result<()> {
    std::fs::write(path, value)
        .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
}

fn read(path: &Path) -> io::Result<String> {
    std::fs::read_to_string(path)
        .map(|s| s.trim().to_string())
        .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
}

impl SimChip {
    /// A chip labelled `label` with `lines` lines, the `names` given (offset, name).
    pub fn new(label: &str, lines: u32, names: &[(u32, &str)]) -> io::Result<SimChip> {
        let dir = Path::new(CONFIGFS).join(label);
        let bank = dir.join("bank0");
        std::fs::create_dir_all(&bank)
            .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", bank.display())))?;
        write(&bank.join("num_lines"), &lines.to_string())?;
        write(&bank.join("label"), label)?;
        for (offset, name) in names {
            let line = bank.join(format!("line{offset}"));
            std::fs::create_dir_all(&line)?;
            write(&line.join("name"), name)?;
        }
        write(&dir.join("live"), "1")?;
        Ok(SimChip {
            dev_name: read(&dir.join("dev_name"))?,
            chip_name: read(&bank.join("chip_name"))?,
            label: label.to_string(),
            names: names.iter().map(|(o, _)| *o).collect(),
            lines,
            dir,
        })
    }

    /// The chip's character device.
    pub fn path(&self) -> PathBuf {
        Path::new("/dev").join(&self.chip_name)
    }

    fn attr(&self, offset: u32, what: &str) -> PathBuf {
        Path::new("/sys/devices/platform")
            .join(&self.dev_name)
            .join(&self.chip_name)
            .join(format!("sim_gpio{offset}"))
            .join(what)
    }

    /// Drives input `offset` from outside: pulled up (high) or down (low).
    pub fn pull(&self, offset: u32, high: bool) -> io::Result<()> {
        write(
            &self.attr(offset, "pull"),
            if high { "pull-up" } else { "pull-down" },
        )
    }

    /// The level of line `offset` as the chip has it (an output's driven level).
    pub fn value(&self, offset: u32) -> io::Result<bool> {
        Ok(read(&self.attr(offset, "value"))? == "1")
    }

    /// Takes the chip away, as an unplugged USB adapter goes: its character device and
    /// lines disappear (requests on them fail with `ENODEV`).
    pub fn unplug(&mut self) -> io::Result<()> {
        write(&self.dir.join("live"), "0")
    }

    /// Brings the chip back after [`unplug`](Self::unplug), its lines at their default
    /// pulls; `chip_name` and `dev_name` are what the kernel gives it now.
    pub fn plug(&mut self) -> io::Result<()> {
        write(&self.dir.join("live"), "1")?;
        self.dev_name = read(&self.dir.join("dev_name"))?;
        self.chip_name = read(&self.dir.join("bank0").join("chip_name"))?;
        Ok(())
    }

    /// The chip's first global GPIO number (what the kernel's `gpio` trace events call its
    /// line 0), from `/sys/class/gpio`.
    pub fn base(&self) -> io::Result<u32> {
        for entry in std::fs::read_dir("/sys/class/gpio")? {
            let dir = entry?.path();
            if dir.join("label").exists() && read(&dir.join("label"))? == self.label {
                return read(&dir.join("base"))?
                    .parse()
                    .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, format!("{e}")));
            }
        }
        Err(io::Error::new(
            io::ErrorKind::NotFound,
            format!("no /sys/class/gpio/gpiochip* is labelled {:?}", self.label),
        ))
    }

    /// Lines `a` and `b` driven from outside as an encoder's channels (both start low).
    pub fn quadrature(&self, a: u32, b: u32) -> io::Result<QuadratureDrive> {
        let open = |offset: u32| {
            let path = self.attr(offset, "pull");
            std::fs::OpenOptions::new()
                .write(true)
                .open(&path)
                .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
        };
        Ok(QuadratureDrive {
            a: open(a)?,
            b: open(b)?,
            phase: 0,
        })
    }

    /// The number of lines.
    pub fn lines(&self) -> u32 {
        self.lines
    }
}

impl Drop for SimChip {
    fn drop(&mut self) {
        let _ = std::fs::write(self.dir.join("live"), "0");
        let bank = self.dir.join("bank0");
        for o in &self.names {
            let _ = std::fs::remove_dir(bank.join(format!("line{o}")));
        }
        let _ = std::fs::remove_dir(&bank);
        let _ = std::fs::remove_dir(&self.dir);
    }
}

/// An encoder's A and B channels driven through two gpio-sim lines' pulls: each count one
/// edge, A leading for counts forward. Each edge is one `write(2)` to an open sysfs file.
#[derive(Debug)]
pub struct QuadratureDrive {
    a: std::fs::File,
    b: std::fs::File,
    /// 0..4: the phase of (A, B) in the forward order 00, 10, 11, 01.
    phase: i64,
}

impl QuadratureDrive {
    /// Moves by `counts` (negative: backward) as fast as the writes go.
    pub fn step(&mut self, counts: i64) -> io::Result<()> {
        self.paced(counts, Duration::ZERO).map(|_| ())
    }

    /// Moves by `counts`, one edge every `gap` at the earliest (spinning, not sleeping);
    /// returns how long it took.
    pub fn paced(&mut self, counts: i64, gap: Duration) -> io::Result<Duration> {
        let dir = counts.signum();
        let start = Instant::now();
        for i in 0..counts.unsigned_abs() {
            if !gap.is_zero() {
                let due = start + gap.saturating_mul(u32::try_from(i).unwrap_or(u32::MAX));
                while Instant::now() < due {
                    std::hint::spin_loop();
                }
            }
            let from = self.phase;
            self.phase = (self.phase + dir).rem_euclid(4);
            // Forward, A changes entering phases 1 and 3; backward, leaving them.
            let a_moves = if dir > 0 {
                self.phase % 2 == 1
            } else {
                from % 2 == 1
            };
            let (a, b) =
                [(false, false), (true, false), (true, true), (false, true)][self.phase as usize];
            let (file, level) = if a_moves { (&self.a, a) } else { (&self.b, b) };
            let text: &[u8] = if level { b"pull-up" } else { b"pull-down" };
            file.write_all_at(text, 0)?;
        }
        Ok(start.elapsed())
    }
}

const TRACING: &str = "/sys/kernel/tracing";

/// The kernel's `gpio_value` and `gpio_direction` trace events from [`GpioTrace::start`]
/// on: every level gpiolib drives on any line, in order, whoever asks — the independent
/// witness that a line was never driven to a level nobody asked for. Tracing stops when
/// dropped.
#[derive(Debug)]
pub struct GpioTrace(());

impl GpioTrace {
    /// Mounts tracefs when needed, clears the trace buffer and turns both events on.
    pub fn start() -> io::Result<GpioTrace> {
        let root = Path::new(TRACING);
        if !root.join("events").exists() {
            let status = std::process::Command::new("mount")
                .args(["-t", "tracefs", "nodev", TRACING])
                .status()?;
            if !status.success() {
                return Err(io::Error::other(format!("mount -t tracefs: {status}")));
            }
        }
        write(&root.join("trace"), "")?;
        for event in ["gpio_value", "gpio_direction"] {
            write(&root.join("events/gpio").join(event).join("enable"), "1")?;
        }
        Ok(GpioTrace(()))
    }

    /// The events of global GPIO number `gpio` so far, in order, as the kernel words them
    /// after the number: `"set 1"`, `"get 0"`, `"out (0)"`, `"in (0)"`.
    pub fn events(&self, gpio: u32) -> io::Result<Vec<String>> {
        let text = read(&Path::new(TRACING).join("trace"))?;
        let prefix = format!("{gpio} ");
        Ok(text
            .lines()
            .filter_map(|l| {
                let (_, rest) = l
                    .split_once("gpio_value: ")
                    .or_else(|| l.split_once("gpio_direction: "))?;
                rest.strip_prefix(&prefix).map(str::to_string)
            })
            .collect())
    }

    /// The levels driven on `gpio` and its direction changes so far: [`events`](Self::events)
    /// without the reads (`"get …"`).
    pub fn driven(&self, gpio: u32) -> io::Result<Vec<String>> {
        Ok(self
            .events(gpio)?
            .into_iter()
            .filter(|e| !e.starts_with("get"))
            .collect())
    }

    /// The ThreadScope pulses driven on `gpio` after its request (its `"set 0"`,
    /// `"out (0)"`): without any lows leading them — the card's own bus thread requests
    /// the lines inside its first pulse, whose end writes low to a line just made low.
    pub fn pulses(&self, gpio: u32) -> io::Result<Vec<String>> {
        Ok(self
            .driven(gpio)?
            .into_iter()
            .skip(2)
            .skip_while(|e| e == "set 0")
            .collect())
    }
}

/// `Ok` when `pulses` (from [`GpioTrace::pulses`]) are ThreadScope's: high while a thread
/// steps, low between, strictly alternating, low at the end; else what breaks that.
pub fn check_pulses(pulses: &[String]) -> Result<(), String> {
    for (i, e) in pulses.iter().enumerate() {
        let want = if i % 2 == 0 { "set 1" } else { "set 0" };
        if e != want {
            return Err(format!("event {i} is {e:?}, not {want:?}: {pulses:?}"));
        }
    }
    if pulses.len() % 2 == 1 {
        return Err(format!("left high: {pulses:?}"));
    }
    Ok(())
}

impl Drop for GpioTrace {
    fn drop(&mut self) {
        for event in ["gpio_value", "gpio_direction"] {
            let _ = std::fs::write(
                Path::new(TRACING)
                    .join("events/gpio")
                    .join(event)
                    .join("enable"),
                "0",
            );
        }
    }
}
