//! The third-party programs hwgw's tests run as peers, declared in one place, and installed
//! by the tests themselves when missing: a test that needs a peer calls [`require`] (or
//! [`ensure`]) first. As root with apt, a missing peer is installed with exactly the
//! Debian packages it needs; otherwise — or when installing fails — the test fails (never
//! skips) naming the packages.

use std::process::Command;

/// Debian's Python, the one Debian's python3-* packages install for (a `python3` earlier
/// on the PATH, such as pyenv's, does not see them).
pub const PYTHON: &str = "/usr/bin/python3";

/// How to tell a peer is there.
#[derive(Debug, Clone, Copy)]
pub enum Probe {
    /// A command on the PATH (or in /usr/sbin, /sbin).
    Command(&'static str),
    /// Python modules that must import in [`PYTHON`] (comma-separated, as `import` takes
    /// them).
    Python(&'static str),
    /// Files packages install (headers, libraries): all of them.
    Files(&'static [&'static str]),
}

/// A third-party peer of the tests.
#[derive(Debug, Clone, Copy)]
pub struct Peer {
    /// What it is, for messages.
    pub name: &'static str,
    /// How to tell it is installed.
    pub probe: Probe,
    /// The Debian packages it takes, including what its package only *Recommends* but the
    /// tests need (installs are made with `--no-install-recommends`).
    pub packages: &'static [&'static str],
    /// Services its packages enable and start that the tests do not want running (the
    /// tests start the program themselves): disabled and stopped once installed.
    pub services: &'static [&'static str],
}

/// A Modbus TCP/RTU server from Debian's pymodbus. Its package imports `serial` and
/// `serial_asyncio`, which it only Recommends.
pub const PYMODBUS: Peer = Peer {
    name: "pymodbus",
    probe: Probe::Python("pymodbus, serial, serial_asyncio"),
    packages: &[
        "python3-pymodbus",
        "python3-serial",
        "python3-serial-asyncio",
    ],
    services: &[],
};

/// mbpoll, a libmodbus master.
pub const MBPOLL: Peer = Peer {
    name: "mbpoll",
    probe: Probe::Command("mbpoll"),
    packages: &["mbpoll"],
    services: &[],
};

/// socat, for pty pairs.
pub const SOCAT: Peer = Peer {
    name: "socat",
    probe: Probe::Command("socat"),
    packages: &["socat"],
    services: &[],
};

/// can-utils: candump, cansend, cangen.
pub const CAN_UTILS: Peer = Peer {
    name: "can-utils",
    probe: Probe::Command("candump"),
    packages: &["can-utils"],
    services: &[],
};

/// i2c-tools: i2cget, i2cset, i2cdump, i2cdetect (in /usr/sbin).
pub const I2C_TOOLS: Peer = Peer {
    name: "i2c-tools",
    probe: Probe::Command("i2cget"),
    packages: &["i2c-tools"],
    services: &[],
};

/// cyclictest, the wake-up latency reference of the jitter benchmark.
pub const CYCLICTEST: Peer = Peer {
    name: "cyclictest",
    probe: Probe::Command("cyclictest"),
    packages: &["rt-tests"],
    services: &[],
};

/// strace, which the real-time system-call bench attaches to one thread at a time.
pub const STRACE: Peer = Peer {
    name: "strace",
    probe: Probe::Command("strace"),
    packages: &["strace"],
    services: &[],
};

/// libsimavr and its parts (uart_pty), with what the Uno harness is compiled with: a C
/// compiler and libelf, which simavr's static library needs (`pkg-config simavr` fails
/// without libelf's .pc, so the flags are given by hand).
pub const SIMAVR: Peer = Peer {
    name: "simavr",
    // Headers: the same paths on every architecture (the libraries' are not).
    probe: Probe::Files(&[
        "/usr/include/simavr/parts/uart_pty.h",
        "/usr/include/libelf.h",
    ]),
    packages: &["libsimavr-dev", "libelf-dev", "gcc", "libc6-dev"],
    services: &[],
};

/// npm, which fetches the StandardFirmata build the tests run.
pub const NPM: Peer = Peer {
    name: "npm",
    probe: Probe::Command("npm"),
    packages: &["npm"],
    services: &[],
};

/// sigrok-cli, which reads ThreadScope's VCD recordings (its `counter` decoder counts
/// each thread's pulses; the decoders come with its libsigrokdecode dependency).
pub const SIGROK: Peer = Peer {
    name: "sigrok-cli",
    probe: Probe::Command("sigrok-cli"),
    packages: &["sigrok-cli"],
    services: &[],
};

/// Debian's Python with pip and pyserial: pyfirmata2 (from PyPI) is installed with them.
pub const PYSERIAL: Peer = Peer {
    name: "pyserial and pip",
    probe: Probe::Python("serial, pip"),
    packages: &["python3-serial", "python3-pip"],
    services: &[],
};

/// Debian's Python with pip: PyPI packages the tests compare with are installed with it
/// ([`crate::pypi`]).
pub const PIP: Peer = Peer {
    name: "pip",
    probe: Probe::Python("pip"),
    packages: &["python3-pip"],
    services: &[],
};

/// iproute2's `ip`: network namespaces and veth pairs for the tests' own hosts.
pub const IPROUTE2: Peer = Peer {
    name: "iproute2",
    probe: Probe::Command("ip"),
    packages: &["iproute2"],
    services: &[],
};

/// The openssl command, which makes the certificates of the TLS tests.
pub const OPENSSL: Peer = Peer {
    name: "openssl",
    probe: Probe::Command("openssl"),
    packages: &["openssl"],
    services: &[],
};

/// man-db: `man` renders the manual pages the hwgw package installs.
pub const MAN_DB: Peer = Peer {
    name: "man-db",
    probe: Probe::Command("man"),
    packages: &["man-db"],
    services: &[],
};

/// bash-completion: the loader that finds a command's completion in
/// /usr/share/bash-completion/completions/ when it is first completed.
pub const BASH_COMPLETION: Peer = Peer {
    name: "bash-completion",
    probe: Probe::Files(&["/usr/share/bash-completion/bash_completion"]),
    packages: &["bash-completion"],
    services: &[],
};

/// lintian, Debian's package checker (on the hwgw package).
pub const LINTIAN: Peer = Peer {
    name: "lintian",
    probe: Probe::Command("lintian"),
    packages: &["lintian"],
    services: &[],
};

/// Prometheus: `promtool` checks an exposition, the server scrapes one (Debian's
/// `prometheus` package has both).
pub const PROMETHEUS: Peer = Peer {
    name: "prometheus",
    probe: Probe::Command("promtool"),
    packages: &["prometheus"],
    // Debian's package enables and starts a Prometheus on 0.0.0.0:9090 (and the kernel
    // rig's guests, which boot this machine's root, would start it too).
    services: &["prometheus"],
};

/// Eclipse Mosquitto, the MQTT broker, and its command-line clients (`mosquitto_sub`,
/// `mosquitto_pub`).
pub const MOSQUITTO: Peer = Peer {
    name: "mosquitto",
    probe: Probe::Files(&[
        "/usr/sbin/mosquitto",
        "/usr/bin/mosquitto_sub",
        "/usr/bin/mosquitto_pub",
    ]),
    packages: &["mosquitto", "mosquitto-clients"],
    // Debian's package enables and starts a broker on port 1883.
    services: &["mosquitto"],
};

/// Headless Chromium and its WebDriver, which selenium drives.
pub const CHROMIUM: Peer = Peer {
    name: "chromium and chromedriver",
    probe: Probe::Command("chromedriver"),
    packages: &["chromium", "chromium-driver"],
    services: &[],
};

/// Why a peer is not there.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{peer} is missing and could not be installed: {why} (install the Debian packages: apt-get install {packages})"
)]
pub struct PeerError {
    /// The peer.
    pub peer: &'static str,
    /// Its packages, space-separated.
    pub packages: String,
    /// What went wrong.
    pub why: String,
}

/// True when `peer` is installed.
pub fn present(peer: &Peer) -> bool {
    match peer.probe {
        Probe::Command(c) => kernel_rig::prepare::which(c),
        Probe::Files(f) => f.iter().all(|f| std::path::Path::new(f).is_file()),
        Probe::Python(modules) => Command::new(PYTHON)
            .args(["-c", &format!("import {modules}")])
            .output()
            .is_ok_and(|o| o.status.success()),
    }
}

/// Makes sure `peer` is installed: installs its packages when it is missing (as root,
/// with apt), then checks again.
pub fn require(peer: &Peer) -> Result<(), PeerError> {
    if present(peer) {
        return Ok(());
    }
    let error = |why: String| PeerError {
        peer: peer.name,
        packages: peer.packages.join(" "),
        why,
    };
    kernel_rig::prepare::apt_install(peer.packages).map_err(|e| error(e.to_string()))?;
    for service in peer.services {
        // Without systemd running (a container), `disable` still removes the links.
        let _ = Command::new("systemctl")
            .args(["disable", "--now", service])
            .output();
    }
    if present(peer) {
        Ok(())
    } else {
        Err(error("installed, but still not usable".into()))
    }
}

/// [`require`], failing the test with its error.
#[track_caller]
pub fn ensure(peer: &Peer) {
    if let Err(e) = require(peer) {
        panic!("{e}");
    }
}
