//! Python packages from PyPI that the tests compare with, pinned, installed for Debian's
//! Python into the peers directory (never into the system's site-packages): put the
//! returned directory on `PYTHONPATH`. pip comes from Debian (`python3-pip`), installed
//! when missing.

use crate::cache::{cached, peer_dir, run};
use crate::peers::{PIP, PYTHON, ensure};
use std::io;
use std::path::PathBuf;
use std::process::Command;

/// cantools and its dependencies, pinned: the independent DBC reader and decoder.
pub const CANTOOLS: &[&str] = &[
    "cantools==45.1.0",
    "argparse_addons==0.12.0",
    "bitstruct==8.24.0",
    "crccheck==1.3.1",
    "packaging==26.3",
    "python-can==4.6.1",
    "textparser==0.26.2",
    "typing_extensions==4.16.0",
    "wrapt==1.17.3",
];

/// `requirements` (exact pins, dependencies listed: nothing else is fetched) installed
/// into the peers directory's `name`, once: the directory to put on `PYTHONPATH`.
pub fn install(name: &str, requirements: &[&str]) -> io::Result<PathBuf> {
    ensure(&PIP);
    let dir = peer_dir().join(name);
    let marker = dir.join("installed");
    cached(&marker, |tmp| {
        run(Command::new(PYTHON)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "--no-deps",
                "--target",
                &dir.to_string_lossy(),
            ])
            .args(requirements))?;
        std::fs::write(tmp, requirements.join("\n"))
    })?;
    Ok(dir)
}

/// cantools ([`CANTOOLS`]): the directory to put on `PYTHONPATH`.
pub fn cantools() -> io::Result<PathBuf> {
    install("cantools-45.1.0", CANTOOLS)
}

/// mqtt-spb-wrapper and what it pins, exactly: the Sparkplug B protobuf module (and
/// paho-mqtt, the MQTT client) of the independent Sparkplug host application. paho-mqtt
/// 1.6.1 is a source package only: pip builds it with Debian's setuptools, which
/// `python3-pip` depends on.
pub const SPARKPLUG: &[&str] = &[
    "mqtt-spb-wrapper==2.1.2",
    "paho-mqtt==1.6.1",
    "protobuf==3.20.3",
];

/// mqtt-spb-wrapper ([`SPARKPLUG`]): the directory to put on `PYTHONPATH`.
pub fn sparkplug() -> io::Result<PathBuf> {
    install("mqtt-spb-wrapper-2.1.2", SPARKPLUG)
}

/// The `mcap` package, the independent MCAP reader. Its codecs (`lz4`, `zstandard`) are
/// left out: hwgw writes uncompressed chunks, which it reads without them.
pub const MCAP: &[&str] = &["mcap==1.6.0"];

/// mcap ([`MCAP`]): the directory to put on `PYTHONPATH`.
pub fn mcap() -> io::Result<PathBuf> {
    install("mcap-1.6.0", MCAP)
}

/// selenium and its dependencies, pinned (for Debian 12's Python 3.11): the browser
/// automation the web page's test drives headless Chromium with (its chromedriver is
/// Debian's, named to it, so Selenium Manager fetches nothing).
pub const SELENIUM: &[&str] = &[
    "selenium==4.51.0",
    "PySocks==1.7.1",
    "attrs==26.1.0",
    "certifi==2026.10.19.post1",
    "h11==0.16.0",
    "idna==3.20",
    "outcome==1.3.0.post0",
    "sniffio==1.3.1",
    "sortedcontainers==2.4.0",
    "trio==0.35.0",
    "trio_websocket==0.12.2",
    "typing_extensions==4.16.0",
    "urllib3==2.8.0",
    "websocket_client==1.9.2",
    "wsproto==1.3.2",
];

/// selenium ([`SELENIUM`]): the directory to put on `PYTHONPATH`.
pub fn selenium() -> io::Result<PathBuf> {
    install("selenium-4.51.0", SELENIUM)
}

/// asyncua (FreeOpcUa's OPC UA stack for Python) and its dependencies, pinned (for
/// Debian 12's Python 3.11): the independent OPC UA client. `cryptography` and `cffi`
/// are manylinux wheels.
pub const ASYNCUA: &[&str] = &[
    "asyncua==2.1.0",
    "aiosqlite==0.22.1",
    "anyio==4.16.0",
    "cffi==2.1.1",
    "cryptography==50.0.2",
    "idna==3.20",
    "pycparser==3.12",
    "python-dateutil==4.0.0",
    "pytz==2026.6",
    "sortedcontainers==2.4.0",
    "typing_extensions==4.16.0",
    "tzdata==2026.6",
    "wait_for2==0.4.1",
];

/// asyncua ([`ASYNCUA`]): the directory to put on `PYTHONPATH`.
pub fn asyncua() -> io::Result<PathBuf> {
    install("asyncua-2.1.0", ASYNCUA)
}

/// Python canopen and what it needs, pinned: the independent CANopen stack (its EDS
/// reader, and later its nodes on vcan).
pub const CANOPEN: &[&str] = &[
    "canopen==2.4.1",
    "python-can==4.6.1",
    "packaging==26.3",
    "typing_extensions==4.16.0",
    "wrapt==1.17.3",
];

/// canopen ([`CANOPEN`]): the directory to put on `PYTHONPATH`.
pub fn canopen() -> io::Result<PathBuf> {
    install("canopen-2.4.1", CANOPEN)
}
