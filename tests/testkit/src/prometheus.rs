//! A real Prometheus server (Debian's `prometheus`) as a peer: it scrapes one target
//! every second into a storage of its own, and answers queries over its HTTP API;
//! killed when dropped. And `promtool check metrics` on an exposition.

use crate::TempDir;
use crate::http::{encode, get};
use crate::peers::{PROMETHEUS, ensure};
use serde_json::Value;
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A running Prometheus; killed when dropped.
pub struct Prometheus {
    child: Child,
    /// Where its HTTP API listens.
    pub addr: SocketAddr,
    dir: TempDir,
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Prometheus {
    /// Prometheus scraping `target`'s `/metrics` every second (job `hwgw`), once it is
    /// ready. Panics, saying why, when it does not become ready.
    pub fn start(target: SocketAddr) -> Prometheus {
        ensure(&PROMETHEUS);
        let dir = TempDir::new("prometheus");
        let config = dir.path().join("prometheus.yml");
        let text = format!(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n\
             scrape_configs:\n  - job_name: hwgw\n    static_configs:\n      - targets: ['{target}']\n"
        );
        std::fs::write(&config, text).unwrap_or_else(|e| panic!("{}: {e}", config.display()));
        let addr = SocketAddr::from(([127, 0, 0, 1], crate::free_port()));
        let log = std::fs::File::create(dir.path().join("prometheus.log"))
            .unwrap_or_else(|e| panic!("prometheus.log: {e}"));
        let child = Command::new("prometheus")
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("data").display()
            ))
            .arg(format!("--web.listen-address={addr}"))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run prometheus: {e}"));
        let mut p = Prometheus { child, addr, dir };
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Ok(a) = crate::http::request(addr, "GET", "/-/ready", &[], b"")
                && a.status == 200
            {
                return p;
            }
            if let Ok(Some(status)) = p.child.try_wait() {
                panic!("prometheus exited ({status}): {}", p.log());
            }
            assert!(
                Instant::now() < deadline,
                "prometheus was not ready in 60 s: {}",
                p.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// What it logged.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("prometheus.log")).unwrap_or_default()
    }

    /// The result vector of instant query `q`: (labels, value) of each series.
    pub fn query(&self, q: &str) -> Vec<(Value, f64)> {
        let a = get(self.addr, &format!("/api/v1/query?query={}", encode(q)));
        let v = a.json();
        assert_eq!(v["status"], "success", "query {q}: {v}");
        v["data"]["result"]
            .as_array()
            .unwrap_or_else(|| panic!("query {q}: {v}"))
            .iter()
            .map(|r| {
                let value = r["value"][1].as_str().and_then(|s| s.parse().ok());
                (r["metric"].clone(), value.unwrap_or(f64::NAN))
            })
            .collect()
    }
}

/// `promtool check metrics` on `text`: Ok, or what it said.
pub fn check_metrics(text: &str) -> Result<(), String> {
    ensure(&PROMETHEUS);
    let mut child = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot run promtool: {e}"))?;
    if let Some(mut stdin) = child.stdin.take() {
        std::io::Write::write_all(&mut stdin, text.as_bytes())
            .map_err(|e| format!("promtool's input: {e}"))?;
    }
    let out = child
        .wait_with_output()
        .map_err(|e| format!("promtool: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "promtool check metrics ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}
