//! Two hosts of the test's own: network namespaces joined by a veth pair, made by the test
//! and gone when dropped, so traffic between gateways never leaves the machine and a link
//! can be cut (`ip link set … down`) without touching anything else.
//!
//! Each namespace is held by a `unshare --net sleep` process and entered with `nsenter
//! --net` (util-linux): no named namespaces under `/run/netns`, no mounts, so this works
//! in a chroot or container as on a host. Killing the holders ends the namespaces, and the
//! veth pair with them.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Runs `PROGRAM ARGS`; its error output on failure.
fn run(program: &str, args: &[&str]) -> Result<(), String> {
    let o = Command::new(program)
        .args(args)
        .output()
        .map_err(|e| format!("{program} {}: {e}", args.join(" ")))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{program} {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        ))
    }
}

/// A's address.
pub const ADDR_A: &str = "10.77.0.1";
/// B's address.
pub const ADDR_B: &str = "10.77.0.2";

/// One namespace, held by a process that sleeps in it.
struct Holder {
    child: Child,
    /// `--net=/proc/PID/ns/net`.
    net: String,
}

impl Holder {
    fn new() -> Result<Holder, String> {
        let child = Command::new("unshare")
            .args(["--net", "sleep", "infinity"])
            .stdin(Stdio::null())
            .spawn()
            .map_err(|e| format!("unshare --net: {e}"))?;
        let ns = format!("/proc/{}/ns/net", child.id());
        let holder = Holder {
            net: format!("--net={ns}"),
            child,
        };
        // unshare(2) happens in the child after spawn returns: wait until its namespace
        // is not ours any more.
        let ours = std::fs::read_link("/proc/self/ns/net").map_err(|e| e.to_string())?;
        let end = Instant::now() + Duration::from_secs(10);
        while std::fs::read_link(&ns).map_err(|e| format!("{ns}: {e}"))? == ours {
            if Instant::now() > end {
                return Err("unshare --net made no namespace within 10 s".into());
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Ok(holder)
    }

    /// Runs `ip ARGS` in the namespace.
    fn ip(&self, args: &[&str]) -> Result<(), String> {
        run("nsenter", &[&[self.net.as_str(), "ip"][..], args].concat())
    }
}

impl Drop for Holder {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Namespaces A and B, their veth ends addressed [`ADDR_A`]/24 and [`ADDR_B`]/24.
pub struct Pair {
    a: Holder,
    b: Holder,
    veth_a: String,
    veth_b: String,
}

impl Pair {
    /// Makes the pair: needs root, iproute2 ([`crate::peers::IPROUTE2`]) and util-linux's
    /// `unshare` and `nsenter`. `tag` names nothing: the veth ends are named after this
    /// process, in the root namespace only for a moment.
    pub fn new(tag: &str) -> Result<Pair, String> {
        crate::peers::require(&crate::peers::IPROUTE2).map_err(|e| e.to_string())?;
        let _ = tag;
        let pid = std::process::id() % 1_000_000_000;
        // Interface names have at most 15 bytes.
        let (veth_a, veth_b) = (format!("hv{pid}a"), format!("hv{pid}b"));
        let (a, b) = (Holder::new()?, Holder::new()?);
        // Made inside A with its peer end in B: never in the machine's own namespace.
        let pid_b = b.child.id().to_string();
        a.ip(&[
            "link", "add", &veth_a, "type", "veth", "peer", "name", &veth_b, "netns", &pid_b,
        ])?;
        let pair = Pair {
            a,
            b,
            veth_a,
            veth_b,
        };
        for (h, dev, addr) in [
            (&pair.a, &pair.veth_a, ADDR_A),
            (&pair.b, &pair.veth_b, ADDR_B),
        ] {
            h.ip(&["addr", "add", &format!("{addr}/24"), "dev", dev])?;
            h.ip(&["link", "set", dev, "up"])?;
            h.ip(&["link", "set", "lo", "up"])?;
        }
        Ok(pair)
    }

    /// The command prefix that runs a program in A's namespace (it execs the program:
    /// the pid and signals are the program's).
    pub fn exec_a(&self) -> [&str; 2] {
        ["nsenter", &self.a.net]
    }

    /// The same in B's namespace.
    pub fn exec_b(&self) -> [&str; 2] {
        ["nsenter", &self.b.net]
    }

    /// Cuts (`up = false`) or restores the link, at both ends.
    pub fn link(&self, up: bool) -> Result<(), String> {
        let state = if up { "up" } else { "down" };
        self.a.ip(&["link", "set", &self.veth_a, state])?;
        self.b.ip(&["link", "set", &self.veth_b, state])
    }
}
