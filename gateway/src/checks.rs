//! Checks the build makes beyond what the types say: bounds on every number a deployment
//! gives (so nothing it says can panic, hang or allocate without bound), and connections
//! that would make components wake each other for ever.

use crate::config::{ConnectionConfig, Deployment};
use crate::problems::KeyPath;
use rtt::{ActivitySpec, Runtime};
use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};
use std::time::Duration;

/// The longest period or time a deployment may give, ms (a day).
pub const MAX_MS: f64 = 86_400_000.0;

/// A number as people read it: `1e308`, not 309 digits (see
/// [`device_interface::text::Number`]).
pub fn number(v: f64) -> String {
    device_interface::text::Number(v).to_string()
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
            format!("{} s: expected 1 to 86400 seconds", number(s)),
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
        let is_component = |name: &str| runtime.component(name).is_ok();
        let (Some((from, out)), Some((to, port))) = (
            crate::config::split_port_among(&c.from, &is_component),
            crate::config::split_port_among(&c.to, &is_component),
        ) else {
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

/// The built-in component types that write a file, and the property naming it.
pub const FILE_WRITERS: [(&str, &str); 2] = [("recorder", "file"), ("reporter", "file")];

/// Files the deployment has hwgw write that are one file: the control socket, the
/// ThreadScope recording (relative to the deployment's folder, `base`: its name and the
/// numbered files each run makes of it, `threads-N.vcd`) and each recorder's and
/// reporter's file (relative to the working directory, as they open them). Two writers of
/// one file would overwrite each other or refuse to start; each later one is reported, as
/// (its key, message), naming the first.
pub fn shared_files(d: &Deployment, base: &Path) -> Vec<(KeyPath, String)> {
    // (key, what it is, path, whether the path names numbered files)
    let mut files: Vec<(KeyPath, String, PathBuf, bool)> = Vec::new();
    if let Some(s) = d.control_socket.as_deref().filter(|s| !s.is_empty()) {
        files.push((
            KeyPath::top("control_socket"),
            "the control socket (control_socket)".into(),
            Path::new(s).to_path_buf(),
            false,
        ));
    }
    if let Some(f) = d.thread_scope_vcd.as_deref().filter(|s| !s.is_empty()) {
        files.push((
            KeyPath::top("thread_scope_vcd"),
            "the ThreadScope recording (thread_scope_vcd)".into(),
            base.join(f),
            true,
        ));
    }
    for (i, c) in d.components.iter().enumerate() {
        for (kind, key) in FILE_WRITERS {
            let Some(file) = (c.kind == kind)
                .then(|| c.properties.get(key))
                .flatten()
                .and_then(toml::Value::as_str)
                .filter(|f| !f.is_empty())
            else {
                continue;
            };
            let at = KeyPath::top("component")
                .index(i)
                .key("properties")
                .key(key);
            let what = format!(
                "the file of {kind} {} ({at})",
                device_interface::text::Quoted(&c.name)
            );
            files.push((at, what, Path::new(file).to_path_buf(), false));
        }
    }
    let same: Vec<PathBuf> = files.iter().map(|(_, _, p, _)| same_file(p)).collect();
    let mut out = Vec::new();
    for (j, (key, _, path, numbered)) in files.iter().enumerate() {
        let shown = device_interface::text::Cut(&path.display().to_string()).to_string();
        for (i, (_, what, first, first_numbered)) in files[..j].iter().enumerate() {
            let message = if same[i] == same[j] {
                format!("{shown} is {what} too: give each its own file")
            } else if *first_numbered && is_numbered(&same[j], &same[i]) {
                format!(
                    "{shown} is one of the numbered files ({}, …) of {what}: give each its \
                     own file",
                    rtt::scope::vcd::files::numbered(first, 1).display()
                )
            } else if *numbered && is_numbered(&same[i], &same[j]) {
                format!(
                    "{what}, {}, is one of the numbered files this names ({}, …): give \
                     each its own file",
                    first.display(),
                    rtt::scope::vcd::files::numbered(path, 1).display()
                )
            } else {
                continue;
            };
            out.push((key.clone(), message));
            break;
        }
    }
    out
}

/// True when `file` is one of the numbered files of `base` (`threads-3.vcd` of
/// `threads.vcd`), both as [`same_file`] gives them.
fn is_numbered(file: &Path, base: &Path) -> bool {
    let Some(name) = file.file_name().and_then(|n| n.to_str()) else {
        return false;
    };
    if file.parent() != base.parent() {
        return false;
    }
    name.match_indices('-').any(|(i, _)| {
        let digits: String = name[i + 1..]
            .chars()
            .take_while(char::is_ascii_digit)
            .collect();
        digits
            .parse::<u64>()
            .is_ok_and(|n| rtt::scope::vcd::files::numbered(base, n) == file)
    })
}

/// `path` as one name per file, without touching it: absolute, its folder's links
/// followed where it exists, else `.` and `..` taken out as written.
fn same_file(path: &Path) -> PathBuf {
    let absolute = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir()
            .unwrap_or_else(|_| PathBuf::from("/"))
            .join(path)
    };
    if let (Some(dir), Some(name)) = (absolute.parent(), absolute.file_name())
        && let Ok(dir) = std::fs::canonicalize(dir)
    {
        return dir.join(name);
    }
    let mut clean = PathBuf::new();
    for c in absolute.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                clean.pop();
            }
            other => clean.push(other),
        }
    }
    clean
}
