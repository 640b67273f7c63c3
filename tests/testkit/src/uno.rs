//! An Arduino Uno running the genuine StandardFirmata, simulated: the project's harness
//! (`simavr/uno.c`, compiled here against Debian's libsimavr) loads the prebuilt
//! `StandardFirmata.cpp.hex` that the npm package avrgirl-arduino 5.0.1 ships (fetched at
//! test time with `npm pack`, never committed: LGPL Firmata code inside an MIT package)
//! into an ATmega328P at 16 MHz with AVCC at 5 V, its UART0 on a pty, paced to real time.
//! The test drives its input pins and ADC and reads its output pins through the harness's
//! stdin; pyfirmata2 (PyPI) is the independent client.
//!
//! Facts the tests rely on: the firmware speaks protocol 2.4 at 57600 baud and sends its
//! banner about 1.9 s after it starts; the simulation runs at 0.7–0.95× real time and takes
//! a whole core (timings are loose); simavr 1.6 drives the pins of timer 0's fast PWM (pins
//! 5 and 6) but not the phase-correct PWM of timers 1 and 2, so a PWM duty is seen on 5 and 6.

use crate::cache::{cached, fail, peer_dir, run};
use crate::peers::{NPM, PYSERIAL, SIMAVR, ensure};
use std::io::{self, BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::Duration;

/// The harness's source.
const HARNESS: &str = include_str!("../simavr/uno.c");
/// The npm package whose `junk/hex/uno/` holds the firmware.
const AVRGIRL: &str = "avrgirl-arduino@5.0.1";
/// The pyfirmata2 release the tests compare with.
pub const PYFIRMATA2: &str = "pyFirmata2==2.5.1";

/// StandardFirmata for the Uno, as avrgirl-arduino 5.0.1 ships it (fetched once).
pub fn firmware() -> io::Result<PathBuf> {
    ensure(&NPM);
    let path = peer_dir().join("avrgirl-arduino-5.0.1/StandardFirmata.cpp.hex");
    cached(&path, |tmp| {
        let dir = tmp.with_extension("d");
        std::fs::create_dir_all(&dir)?;
        run(Command::new("npm")
            .args(["pack", AVRGIRL, "--silent"])
            .current_dir(&dir))?;
        run(Command::new("tar")
            .args([
                "xzf",
                "avrgirl-arduino-5.0.1.tgz",
                "package/junk/hex/uno/StandardFirmata.cpp.hex",
            ])
            .current_dir(&dir))?;
        std::fs::rename(
            dir.join("package/junk/hex/uno/StandardFirmata.cpp.hex"),
            tmp,
        )?;
        let _ = std::fs::remove_dir_all(&dir);
        Ok(())
    })
}

/// The harness, compiled once per version of its source.
pub fn harness() -> io::Result<PathBuf> {
    ensure(&SIMAVR);
    let hash = HARNESS.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
    });
    let path = peer_dir().join(format!("simavr-uno/uno-{hash:016x}"));
    cached(&path, |tmp| {
        let src = tmp.with_extension("c");
        std::fs::write(&src, HARNESS)?;
        let out = tmp.to_string_lossy().into_owned();
        let src = src.to_string_lossy().into_owned();
        run(Command::new("cc").args([
            "-O2",
            "-I/usr/include/simavr",
            "-I/usr/include/simavr/parts",
            "-o",
            &out,
            &src,
            "-lsimavrparts",
            "-lsimavr",
            "-lelf",
            "-lpthread",
            "-lutil",
        ]))
    })
}

/// pyfirmata2 installed for Debian's Python (with Debian's pyserial): the directory to
/// put on `PYTHONPATH`.
pub fn pyfirmata2() -> io::Result<PathBuf> {
    ensure(&PYSERIAL);
    crate::pypi::install("pyfirmata2-2.5.1", &[PYFIRMATA2])
}

/// A pin as the harness sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinState {
    /// Its DDR bit: an output.
    pub output: bool,
    /// Its level.
    pub level: bool,
    /// Its duty cycle over its last whole period (its level when it is not toggling).
    pub duty: f64,
    /// That period, µs.
    pub period_us: f64,
    /// Output edges so far.
    pub edges: u64,
}

/// A running simulated Uno. Dropping it kills the simulation.
pub struct SimUno {
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<String>,
    pty: PathBuf,
}

impl SimUno {
    /// Starts an Uno running StandardFirmata; returns once its pty is there (the firmware
    /// sends its banner about 1.9 s later).
    pub fn start() -> io::Result<SimUno> {
        let (harness, hex) = (harness()?, firmware()?);
        let mut child = Command::new(harness)
            .arg(hex)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()?;
        let (stdin, stdout) = match (child.stdin.take(), child.stdout.take()) {
            (Some(i), Some(o)) => (i, o),
            _ => return Err(fail("the harness's pipes")),
        };
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(l) = line.strip_prefix("@ ")
                    && tx.send(l.to_string()).is_err()
                {
                    break;
                }
            }
        });
        let mut uno = SimUno {
            child,
            stdin,
            lines,
            pty: PathBuf::new(),
        };
        let first = uno.next_line()?;
        uno.pty = PathBuf::from(
            first
                .strip_prefix("pty ")
                .ok_or_else(|| fail(format!("the harness said {first:?}, not its pty")))?,
        );
        let ready = uno.next_line()?;
        if ready != "ready" {
            return Err(fail(format!("the harness said {ready:?}, not ready")));
        }
        Ok(uno)
    }

    fn next_line(&self) -> io::Result<String> {
        match self.lines.recv_timeout(Duration::from_secs(20)) {
            Ok(l) => Ok(l),
            Err(RecvTimeoutError::Timeout) => Err(fail("the harness did not answer in 20 s")),
            Err(RecvTimeoutError::Disconnected) => Err(fail("the harness ended")),
        }
    }

    /// Sends a command and returns its answer (the command has taken effect).
    pub fn command(&mut self, cmd: &str) -> io::Result<String> {
        writeln!(self.stdin, "{cmd}")?;
        self.stdin.flush()?;
        let answer = self.next_line()?;
        if let Some(e) = answer.strip_prefix("error ") {
            return Err(fail(format!("harness: {e}")));
        }
        Ok(answer)
    }

    /// The pty the firmware's serial line is on (a `/dev/pts/N` of its own).
    pub fn pty(&self) -> &Path {
        &self.pty
    }

    /// Drives input pin `pin` (Arduino numbering; 14–19 are A0–A5) to `high`.
    pub fn input(&mut self, pin: u8, high: bool) -> io::Result<()> {
        self.command(&format!("in {pin} {}", u8::from(high)))
            .map(drop)
    }

    /// Puts `millivolts` on analog input `channel`.
    pub fn adc(&mut self, channel: u8, millivolts: u32) -> io::Result<()> {
        self.command(&format!("adc {channel} {millivolts}"))
            .map(drop)
    }

    /// A jumper from output pin `from` to input pin `to`.
    pub fn wire(&mut self, from: u8, to: u8) -> io::Result<()> {
        self.command(&format!("wire {from} {to}")).map(drop)
    }

    /// Writes `bytes` to the host's side of the line, between the firmware's messages.
    pub fn inject(&mut self, bytes: &[u8]) -> io::Result<()> {
        let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        self.command(&format!("inject {hex}")).map(drop)
    }

    /// Pin `pin`'s state now.
    pub fn pin(&mut self, pin: u8) -> io::Result<PinState> {
        let a = self.command(&format!("get {pin}"))?;
        let f: Vec<&str> = a.split_whitespace().collect();
        let num = |i: usize| -> io::Result<f64> {
            f.get(i)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| fail(format!("bad pin answer {a:?}")))
        };
        Ok(PinState {
            output: num(3)? != 0.0,
            level: num(5)? != 0.0,
            duty: num(7)?,
            period_us: num(9)?,
            edges: num(11)? as u64,
        })
    }

    /// True while pin `pin` is an input with its pull-up on (the AVR's PORT bit set, its
    /// DDR bit clear).
    pub fn pullup(&mut self, pin: u8) -> io::Result<bool> {
        let a = self.command(&format!("pullup {pin}"))?;
        match a.split_whitespace().nth(2) {
            Some("1") => Ok(true),
            Some("0") => Ok(false),
            _ => Err(fail(format!("bad pullup answer {a:?}"))),
        }
    }

    /// Kills the simulation (the board unplugged: its pty goes away).
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for SimUno {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The millivolts that make the Uno's 10-bit ADC (AVCC 5 V, as simavr converts:
/// `mV × 1023 / 5000`, truncated) read `raw`.
pub fn millivolts_for(raw: u16) -> u32 {
    (u32::from(raw) * 5000).div_ceil(1023)
}
