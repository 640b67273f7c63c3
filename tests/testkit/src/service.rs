//! An `hwgw` binary running a deployment on a control socket of its own, as an operator
//! would run it: started, asked over its socket and its CLI, stopped with SIGTERM.

use serde_json::Value;
use std::ffi::OsStr;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::time::{Duration, Instant};

/// A directory of its own under the temporary directory, removed when dropped.
pub struct TempDir(PathBuf);

impl TempDir {
    /// A new, empty directory named after `tag` and this process.
    pub fn new(tag: &str) -> TempDir {
        let d = std::env::temp_dir().join(format!("hwgw-test-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        if let Err(e) = std::fs::create_dir_all(&d) {
            panic!("{}: {e}", d.display());
        }
        TempDir(d)
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// How a stopped service ended.
#[derive(Debug)]
pub struct Stopped {
    /// Its exit status.
    pub status: ExitStatus,
    /// Everything it logged (its standard error).
    pub log: String,
}

/// A running `hwgw run` (or a user's binary built on `hwgw::cli::main`).
pub struct Service {
    child: Option<Child>,
    bin: PathBuf,
    /// Its control socket.
    pub socket: PathBuf,
    log: PathBuf,
    dir: TempDir,
}

/// `BIN check CONFIG`: what it printed and how it ended.
pub fn check(bin: &str, config: &Path) -> Output {
    Command::new(bin)
        .arg("check")
        .arg(config)
        .output()
        .unwrap_or_else(|e| panic!("{bin}: {e}"))
}

/// How long a service may take to open its socket.
const START: Duration = Duration::from_secs(30);

impl Service {
    /// Starts `BIN run ARGS --socket <a socket of its own>` (ARGS: a deployment file, or
    /// nothing for the embedded default) with extra environment `env`, logging to a file,
    /// and returns once its socket answers.
    pub fn start<S: AsRef<OsStr>>(
        bin: &str,
        tag: &str,
        args: &[S],
        env: &[(&str, &str)],
    ) -> Result<Service, String> {
        Service::start_in(&[], bin, tag, args, env)
    }

    /// [`Service::start`] under `wrapper`, a command that runs the rest of its line in
    /// another context and execs it (`ip netns exec NS`): the process, its pid and its
    /// signals are hwgw's own.
    pub fn start_in<S: AsRef<OsStr>>(
        wrapper: &[&str],
        bin: &str,
        tag: &str,
        args: &[S],
        env: &[(&str, &str)],
    ) -> Result<Service, String> {
        Service::spawn(TempDir::new(tag), wrapper, bin, args, env)
    }

    /// [`Service::start`] of deployment `text`, written into the service's own folder as
    /// `deployment.toml` (see [`Service::deployment`]).
    pub fn run_text(bin: &str, tag: &str, text: &str) -> Result<Service, String> {
        let dir = TempDir::new(tag);
        let file = dir.path().join("deployment.toml");
        std::fs::write(&file, text).map_err(|e| format!("{}: {e}", file.display()))?;
        Service::spawn(dir, &[], bin, &[file], &[])
    }

    /// The deployment file [`Service::run_text`] wrote.
    pub fn deployment(&self) -> PathBuf {
        self.dir.path().join("deployment.toml")
    }

    fn spawn<S: AsRef<OsStr>>(
        dir: TempDir,
        wrapper: &[&str],
        bin: &str,
        args: &[S],
        env: &[(&str, &str)],
    ) -> Result<Service, String> {
        let socket = dir.path().join("hwgw.sock");
        let log = dir.path().join("hwgw.log");
        let log_file =
            std::fs::File::create(&log).map_err(|e| format!("{}: {e}", log.display()))?;
        let mut cmd = match wrapper.split_first() {
            Some((first, rest)) => {
                let mut c = Command::new(first);
                c.args(rest).arg(bin);
                c
            }
            None => Command::new(bin),
        };
        let child = cmd
            .arg("run")
            .args(args)
            .arg("--socket")
            .arg(&socket)
            .env("RUST_LOG", "info")
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .map_err(|e| format!("{bin}: {e}"))?;
        let mut svc = Service {
            child: Some(child),
            bin: PathBuf::from(bin),
            socket,
            log,
            dir,
        };
        let end = Instant::now() + START;
        while UnixStream::connect(&svc.socket).is_err() {
            if let Some(Ok(Some(status))) = svc.child.as_mut().map(|c| c.try_wait()) {
                return Err(format!("{bin} exited ({status}): {}", svc.log_text()));
            }
            if Instant::now() > end {
                return Err(format!("{bin} did not open its socket: {}", svc.log_text()));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(svc)
    }

    /// Its scratch directory (removed with it).
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Its process id.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// What it logged so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// One request line over the socket; the reply line.
    pub fn request(&self, req: Value) -> Value {
        let mut c = UnixStream::connect(&self.socket)
            .unwrap_or_else(|e| panic!("{}: {e}", self.socket.display()));
        let _ = c.set_read_timeout(Some(Duration::from_secs(30)));
        let mut line = req.to_string();
        line.push('\n');
        c.write_all(line.as_bytes())
            .unwrap_or_else(|e| panic!("sending {req}: {e}"));
        let mut reply = String::new();
        BufReader::new(c)
            .read_line(&mut reply)
            .unwrap_or_else(|e| panic!("reply to {req}: {e}"));
        serde_json::from_str(&reply).unwrap_or_else(|e| panic!("reply to {req}: {e}: {reply:?}"))
    }

    /// The `ok` of a request's reply; panics on an error reply.
    pub fn ok(&self, req: Value) -> Value {
        let r = self.request(req.clone());
        r.get("ok")
            .cloned()
            .unwrap_or_else(|| panic!("{req} -> {r}"))
    }

    /// Server `name`'s entry in `status` (`server.web`): its address (`bus`) and
    /// `counters`; panics when it has none.
    pub fn server_status(&self, name: &str) -> Value {
        let s = self.ok(serde_json::json!({"cmd": "status"}));
        s["servers"]
            .as_array()
            .and_then(|l| l.iter().find(|v| v["name"] == name))
            .cloned()
            .unwrap_or_else(|| panic!("no server {name} in {s}"))
    }

    /// Where server `name` listens, as `status` says.
    pub fn server_address(&self, name: &str) -> std::net::SocketAddr {
        let e = self.server_status(name);
        e["bus"]
            .as_str()
            .and_then(|b| b.parse().ok())
            .unwrap_or_else(|| panic!("{name} has no address: {e}"))
    }

    /// Where server `name` listens once it does: until it started, `status` gives its
    /// configured address (port 0, perhaps); this waits for a bound port.
    pub fn wait_listening(&self, name: &str) -> std::net::SocketAddr {
        let mut addr = None;
        crate::wait_until(&format!("{name} listening"), || {
            addr = self.server_status(name)["bus"]
                .as_str()
                .and_then(|b| b.parse::<std::net::SocketAddr>().ok())
                .filter(|a| a.port() != 0);
            addr.is_some()
        });
        addr.unwrap_or_else(|| unreachable!("waited for"))
    }

    /// `BIN ARGS --socket <its socket>`.
    pub fn cli(&self, args: &[&str]) -> Output {
        Command::new(&self.bin)
            .args(args)
            .arg("--socket")
            .arg(&self.socket)
            .output()
            .unwrap_or_else(|e| panic!("{}: {e}", self.bin.display()))
    }

    /// The standard output of `BIN ARGS`, which must succeed.
    pub fn out(&self, args: &[&str]) -> Result<String, String> {
        let o = self.cli(args);
        if !o.status.success() {
            return Err(format!(
                "{} {}: {}",
                self.bin.display(),
                args.join(" "),
                String::from_utf8_lossy(&o.stderr)
            ));
        }
        Ok(String::from_utf8_lossy(&o.stdout).trim().to_string())
    }

    /// Sends `signal` and waits for the exit.
    pub fn stop_with(mut self, signal: nix::sys::signal::Signal) -> Stopped {
        let mut child = self
            .child
            .take()
            .unwrap_or_else(|| panic!("already stopped"));
        let pid = nix::unistd::Pid::from_raw(child.id() as i32);
        let _ = nix::sys::signal::kill(pid, signal);
        let status = child.wait().unwrap_or_else(|e| panic!("waiting: {e}"));
        Stopped {
            status,
            log: self.log_text(),
        }
    }

    /// SIGTERM, then wait for the exit.
    pub fn terminate(self) -> Stopped {
        self.stop_with(nix::sys::signal::Signal::SIGTERM)
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}
