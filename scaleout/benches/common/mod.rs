//! What the Zenoh benches share: a node's configuration on loopback TCP, free ports, and
//! running the bench again as each of its two processes.

use scaleout::ZenohConfig;

/// Node `name`'s configuration: listening on and/or connecting to a loopback endpoint,
/// no gossip, no TLS, publishing every `publish_ms`.
pub fn config(
    name: &str,
    listen: Option<String>,
    connect: Option<String>,
    publish_ms: f64,
) -> ZenohConfig {
    ZenohConfig {
        name: name.into(),
        mode: Default::default(),
        listen: listen.into_iter().collect(),
        connect: connect.into_iter().collect(),
        tls: None,
        gossip: false,
        publish_ms: Some(publish_ms),
        stale_ms: None,
        offline_ms: None,
        lease_ms: None,
        request_timeout_ms: None,
        import: Vec::new(),
        export: Vec::new(),
    }
}

/// A TCP port free on loopback now.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or_else(|e| panic!("{e}"))
}

/// The role this process was spawned for ([`spawn`]) and the two ports it shares with
/// the other: `None` in the parent.
pub fn role() -> Option<(String, (u16, u16))> {
    let role = std::env::var("HWGW_BENCH_ROLE").ok()?;
    let v = std::env::var("HWGW_BENCH_PORTS").unwrap_or_default();
    let (a, b) = v.split_once(',').unwrap_or_else(|| panic!("ports {v}"));
    let p = |s: &str| s.parse().unwrap_or_else(|e| panic!("{s}: {e}"));
    Some((role, (p(a), p(b))))
}

/// Two free ports, as [`spawn`] passes them.
pub fn ports() -> String {
    format!("{},{}", free_port(), free_port())
}

/// This bench again as `role`, sharing `ports`, its standard input and output piped.
pub fn spawn(role: &str, ports: &str) -> std::process::Child {
    let exe = std::env::current_exe().unwrap_or_else(|e| panic!("{e}"));
    std::process::Command::new(&exe)
        .env("HWGW_BENCH_ROLE", role)
        .env("HWGW_BENCH_PORTS", ports)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{e}"))
}
