//! A pymodbus server (Debian's python3-pymodbus, a Modbus implementation we did not write)
//! as a peer: `drivers/modbus/tests/peers/pymodbus_server.py` on a free TCP port, killed
//! when dropped. Installed by the test when missing ([`crate::peers::PYMODBUS`]).

use crate::peers::{PYMODBUS, PYTHON, ensure};
use std::net::{SocketAddr, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The server script (its registers hold the values the modbus tests decode).
pub const SERVER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../drivers/modbus/tests/peers/pymodbus_server.py"
);

/// A running pymodbus server; killed when dropped.
pub struct PyModbus {
    child: Child,
    /// Where it listens.
    pub addr: SocketAddr,
}

impl Drop for PyModbus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl PyModbus {
    /// A server in `mode` (`tcp`, `sparse`: see the script) on a free port, once it
    /// listens. The port is free when picked but may be taken before Python binds it:
    /// three ports are tried. Panics, saying why, when none serves.
    pub fn start(mode: &str) -> PyModbus {
        ensure(&PYMODBUS);
        let mut last = String::new();
        for _ in 0..3 {
            match PyModbus::try_start(mode, crate::free_port()) {
                Ok(p) => return p,
                Err(e) => last = e,
            }
        }
        panic!("{last}");
    }

    /// Stops the server answering (SIGSTOP): a unit that hangs. Its port stays its own, so
    /// [`PyModbus::resume`] brings the same unit back where a server started again on the
    /// freed port could find it taken (by a test's `free_port` elsewhere, or a client's
    /// connection to it that the kernel joined to itself), and pymodbus 3.0 then lives on
    /// without listening.
    pub fn pause(&self) {
        self.signal(nix::sys::signal::Signal::SIGSTOP);
    }

    /// Lets a paused server answer again (SIGCONT): what queued meanwhile is served.
    pub fn resume(&self) {
        self.signal(nix::sys::signal::Signal::SIGCONT);
    }

    fn signal(&self, signal: nix::sys::signal::Signal) {
        let pid = nix::unistd::Pid::from_raw(self.child.id() as i32);
        nix::sys::signal::kill(pid, signal)
            .unwrap_or_else(|e| panic!("cannot send {signal} to the pymodbus server: {e}"));
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    fn try_start(mode: &str, port: u16) -> Result<PyModbus, String> {
        let child = Command::new(PYTHON)
            .args([SERVER, mode, &port.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("cannot run {PYTHON}: {e}"))?;
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let mut peer = PyModbus { child, addr };
        let deadline = Instant::now() + Duration::from_secs(20);
        while TcpStream::connect(addr).is_err() {
            if let Ok(Some(status)) = peer.child.try_wait() {
                let mut err = String::new();
                if let Some(e) = peer.child.stderr.as_mut() {
                    let _ = std::io::Read::read_to_string(e, &mut err);
                }
                return Err(format!(
                    "the pymodbus server exited ({status}); is python3-pymodbus installed?\n{err}"
                ));
            }
            if Instant::now() > deadline {
                return Err(format!("the pymodbus server did not listen on {addr}"));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(peer)
    }
}

/// The pattern `pymodbus_server.py pattern_…` serves (2000 addresses a table): what a
/// test expects at an address, computed as the script does.
pub mod pattern {
    /// Addresses served in each table.
    pub const SIZE: u16 = 2000;

    /// Input register `n`.
    pub fn input_register(n: u16) -> u16 {
        n.wrapping_mul(0x9E37).wrapping_add(0x1234)
    }

    /// Holding register `n`.
    pub fn holding_register(n: u16) -> u16 {
        n.wrapping_mul(0x6C8B).wrapping_add(0x4321)
    }

    /// Discrete input `n`.
    pub fn discrete_input(n: u16) -> bool {
        (u32::from(n) * 7) % 3 == 0
    }

    /// Coil `n`.
    pub fn coil(n: u16) -> bool {
        (u32::from(n) * 5) % 4 == 1
    }
}

/// The master script (`drivers/modbus/tests/peers/pymodbus_client.py`).
pub const CLIENT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../drivers/modbus/tests/peers/pymodbus_client.py"
);

/// A pymodbus master as a peer, driven by JSON lines (see the script for its requests
/// and results); killed when dropped.
pub struct PyMaster(crate::jsonlines::JsonPeer);

impl PyMaster {
    /// A master in `mode` (`tcp`, `rtu_over_tcp`: `at` a port; `serial`: `at` a device, its
    /// baud rate and parity, "DEVICE BAUD N"), once connected. Fails the test when pymodbus cannot
    /// be had or does not connect.
    pub fn connect(mode: &str, at: &str) -> PyMaster {
        ensure(&PYMODBUS);
        let mut cmd = Command::new(PYTHON);
        cmd.arg(CLIENT).arg(mode).args(at.split(' '));
        let mut peer = crate::jsonlines::JsonPeer::spawn(cmd, "the pymodbus master");
        let hello = peer.answer();
        assert_eq!(hello["ready"], true, "the pymodbus master: {hello}");
        PyMaster(peer)
    }

    /// Sends `request`, returns its result.
    pub fn ask(&mut self, request: &serde_json::Value) -> serde_json::Value {
        self.0.ask(request)
    }
}

/// pymodbus's RTU server on serial port `device` (the script's `rtu` mode: units 1 and 2
/// multi-dropped, 19200 baud); killed when dropped. Ready once it answers: wait for a
/// unit's reply.
pub struct PyRtu(Child);

impl PyRtu {
    /// Starts it; fails the test when pymodbus cannot be had or run.
    pub fn start(device: &std::path::Path) -> PyRtu {
        ensure(&PYMODBUS);
        let child = Command::new(PYTHON)
            .arg(SERVER)
            .arg("rtu")
            .arg(device)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {PYTHON} {SERVER}: {e}"));
        PyRtu(child)
    }

    /// Kills it now (a unit that stops answering).
    pub fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for PyRtu {
    fn drop(&mut self) {
        self.kill();
    }
}
