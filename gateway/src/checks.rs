//! Checks the build makes beyond what the types say: bounds on every number a deployment
//! gives (so nothing it says can panic, hang or allocate without bound), and connections
//! that would make components wake each other for ever.

use crate::config::{ConnectionConfig, Deployment, split_port};
use rtt::{ActivitySpec, Runtime};
use std::collections::HashMap;
use std::path::Path;
use std::time::Duration;

/// The longest period or time a deployment may give, ms (a day).
pub const MAX_MS: f64 = 86_400_000.0;

/// A number as people read it: `1e308`, not 309 digits.
pub fn number(v: f64) -> String {
    if v.is_finite() && v.abs() >= 1e15 {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// A period in ms as a duration, if it is one: finite, above 0, at most a day.
pub fn period(ms: f64) -> Result<Duration, String> {
    if !(ms.is_finite() && ms > 0.0) {
        return Err(format!("{} ms: expected a period above 0", number(ms)));
    }
    if ms > MAX_MS {
        return Err(format!(
            "{} ms: expected at most {MAX_MS} ms (a day)",
            number(ms)
        ));
    }
    Ok(Duration::from_secs_f64(ms / 1000.0))
}

/// Problems with the control server's settings, as (key, message).
pub fn control(d: &Deployment) -> Vec<(String, String)> {
    let mut out = Vec::new();
    if let Some(n) = d.control_clients
        && !(1..=1024).contains(&n)
    {
        out.push((
            "control_clients".into(),
            format!("{n}: expected 1 to 1024 clients"),
        ));
    }
    if let Some(s) = d.control_idle_s
        && !(s.is_finite() && (1.0..=86_400.0).contains(&s))
    {
        out.push((
            "control_idle_s".into(),
            format!("{s} s: expected 1 to 86400 seconds"),
        ));
    }
    if let Some(path) = &d.control_socket
        && let Err(e) = crate::socket::check_path(std::path::Path::new(path))
    {
        out.push(("control_socket".into(), e.to_string()));
    }
    out
}

/// Connections that would make event-driven components wake each other for ever: a
/// connection into an event port of a non-periodic (or file-descriptor) component wakes
/// it; a loop of such wake-ups between components that write what they get never stops.
/// Returns (connection index, message) for one connection of each loop.
pub fn spin_loops(connections: &[ConnectionConfig], runtime: &Runtime) -> Vec<(usize, String)> {
    // The wake edges: component -> component, by connection.
    let mut edges: HashMap<&str, Vec<(&str, usize)>> = HashMap::new();
    for (i, c) in connections.iter().enumerate() {
        let (Some((from, out)), Some((to, port))) = (split_port(&c.from), split_port(&c.to)) else {
            continue;
        };
        // Only a connection that can be made: from an output port.
        let from_output = runtime.component(from).is_ok_and(|t| {
            t.ports()
                .iter()
                .any(|p| p.name == out && p.direction == rtt::component::Direction::Output)
        });
        if !from_output {
            continue;
        }
        let Ok(t) = runtime.component(to) else {
            continue;
        };
        let woken = !matches!(
            t.activity().spec(),
            ActivitySpec::Periodic { .. } | ActivitySpec::Slave
        );
        let event = t.ports().iter().any(|p| p.name == port && p.event);
        if woken && event {
            edges.entry(from).or_default().push((to, i));
        }
    }
    // Depth-first search for a way back; each loop reported once, at its closing edge.
    let mut out = Vec::new();
    let mut done: Vec<&str> = Vec::new();
    let mut nodes: Vec<&str> = edges.keys().copied().collect();
    nodes.sort_unstable();
    for start in nodes {
        let mut stack = vec![(start, vec![start])];
        let mut seen = vec![start];
        while let Some((node, path)) = stack.pop() {
            for &(next, i) in edges.get(node).into_iter().flatten() {
                if next == start {
                    if !path.iter().any(|p| done.contains(p)) {
                        let round: Vec<&str> = path.iter().copied().chain([start]).collect();
                        let msg = if path.len() == 1 {
                            format!(
                                "{} -> {}: {start} wakes itself: each value it writes wakes it again, for ever; make it periodic or connect to a port that is not an event port",
                                connections[i].from, connections[i].to
                            )
                        } else {
                            format!(
                                "{} -> {}: these components wake each other for ever ({}); make one of them periodic or connect to a port that is not an event port",
                                connections[i].from,
                                connections[i].to,
                                round.join(" -> ")
                            )
                        };
                        out.push((i, msg));
                    }
                } else if !seen.contains(&next) {
                    seen.push(next);
                    let mut p = path.clone();
                    p.push(next);
                    stack.push((next, p));
                }
            }
        }
        done.push(start);
    }
    out
}

/// Whether a new file can be made at `path` at start, without making it now: it must not
/// exist (never overwritten), and its folder must exist and be writable by this process.
pub fn new_file(path: &Path) -> Result<(), String> {
    let show = path.display();
    if path.file_name().is_none() || path.as_os_str().as_encoded_bytes().ends_with(b"/") {
        return Err(format!("{:?}: expected a file name", show.to_string()));
    }
    if std::fs::symlink_metadata(path).is_ok() {
        return Err(format!(
            "{show} exists: it is never overwritten; remove it or name another file"
        ));
    }
    creatable(path)
}

/// Whether a file `path` that does not exist could be created: its folder exists and this
/// process may write to it.
pub fn creatable(path: &Path) -> Result<(), String> {
    let show = path.display();
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        return Err(format!(
            "{show}: the directory {} does not exist",
            dir.display()
        ));
    }
    nix::unistd::access(dir, nix::unistd::AccessFlags::W_OK)
        .map_err(|e| format!("{show}: cannot create it in {}: {e}", dir.display()))
}
