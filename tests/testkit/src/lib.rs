//! What hwgw's tests share, so no test file carries its own copy.
//!
//! - [`peers`]: the third-party programs the tests talk to, declared in one place and
//!   installed on demand (the suite passes on a fresh machine, or fails naming the
//!   package — it never skips);
//! - [`mod@bench`]: timing cycles and averaging rounds, for the bench binaries;
//! - [`wait`]: waiting for a condition with a deadline;
//! - [`candump`]: a CAN capture that is listening before it returns;
//! - [`mbpoll`]: the libmodbus master as a one-shot check;
//! - [`fixtures`]: shared test data (a Modbus register map);
//! - [`gpiosim`]: chips of the kernel's GPIO simulator, driven from outside;
//! - [`comedi`]: comedi boards attached and detached, the parallel port's writes as qemu
//!   recorded them;
//! - [`i2cstub`]: the kernel's I2C stub, its chips' registers set and read with i2c-tools;
//! - [`uno`]: an Arduino Uno running the genuine StandardFirmata in simavr, its pins driven
//!   and watched; pyfirmata2 as the other client;
//! - [`pypi`]: pinned Python packages the tests compare with (cantools, pyfirmata2, mcap);
//! - [`picture`]: pixel statistics of a PNG picture; [`mcapread`]: an MCAP file read by
//!   the `mcap` package;
//! - [`rng`]: the fuzz tests' seeded random source;
//! - [`rig`]: kernel rig presets (vcan);
//! - [`deb`]: hwgw's Debian packages built from a test's binary, and lintian's report;
//! - [`certs`]: TLS certificates made with openssl;
//! - [`mosquitto`]: an MQTT broker of the test's own, its clients, a Sparkplug host;
//! - [`service`]: an `hwgw` binary running a deployment on a socket of its own;
//! - [`stalls`]: a machine's stalls told from a program's own, two programs on one CPU;
//! - [`logs`]: what a gateway built in the test's own process logs, captured;
//! - [`layout`]: checks of the source tree's shape (module cycles, function lengths).

pub mod bench;
mod cache;
pub mod candump;
pub mod certs;
pub mod comedi;
pub mod deb;
pub mod fixtures;
pub mod gpiosim;
pub mod http;
pub mod i2cstub;
pub mod jsonlines;
pub mod layout;
pub mod logs;
pub mod mbpoll;
pub mod mcapread;
pub mod mosquitto;
pub mod netns;
pub mod opcua;
pub mod peers;
pub mod picture;
pub mod prometheus;
pub mod pty;
pub mod pymodbus;
pub mod pypi;
pub mod rig;
pub mod rng;
pub mod service;
pub mod stalls;
pub mod uno;
pub mod vcd;
pub mod wait;

pub use candump::Candump;
pub use comedi::{ComediBoard, PortTrace};
pub use gpiosim::{GpioTrace, SimChip};
pub use i2cstub::I2cStub;
pub use logs::LogCapture;
pub use service::{Service, TempDir};
pub use uno::SimUno;
pub use wait::{wait_for, wait_until};

/// Runs `program` with `args` and returns its standard output, trimmed; an error carries
/// the command and what it printed (for the peers the kernel-bus helpers drive:
/// `modprobe`, `i2cset`, `comedi_config`, …).
pub fn run(program: &str, args: &[&str]) -> std::io::Result<String> {
    let out = std::process::Command::new(program).args(args).output()?;
    if !out.status.success() {
        return Err(std::io::Error::other(format!(
            "{program} {}: {}{}",
            args.join(" "),
            String::from_utf8_lossy(&out.stdout).trim(),
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Sets this process's soft limit of open file descriptors to `soft` (None: back to the
/// hard limit); returns the soft limit it had. For a test binary of its own that makes
/// `accept` fail with EMFILE.
pub fn set_fd_limit(soft: Option<u64>) -> std::io::Result<u64> {
    use nix::sys::resource::{Resource, getrlimit, setrlimit};
    let (old, hard) = getrlimit(Resource::RLIMIT_NOFILE).map_err(std::io::Error::from)?;
    setrlimit(
        Resource::RLIMIT_NOFILE,
        soft.unwrap_or(hard).min(hard),
        hard,
    )
    .map_err(std::io::Error::from)?;
    Ok(old)
}

/// A TCP port on 127.0.0.1 that was free a moment ago (for a peer that must be told its
/// port before it starts).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or_else(|e| panic!("no free port on 127.0.0.1: {e}"))
}
