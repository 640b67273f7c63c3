//! Two hosts of the test's own: network namespaces joined by a veth pair, made by the test
//! and removed when dropped, so traffic between gateways never leaves the machine and a
//! link can be cut (`ip link set … down`) without touching anything else.

use std::process::Command;

/// Runs `ip ARGS`; its error output on failure.
fn ip(args: &[&str]) -> Result<(), String> {
    let o = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("ip {}: {e}", args.join(" ")))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        ))
    }
}

/// Namespaces `a` and `b`, their veth ends addressed `10.77.0.1/24` and `10.77.0.2/24`.
pub struct Pair {
    /// Namespace A's name.
    pub a: String,
    /// Namespace B's name.
    pub b: String,
    veth_a: String,
    veth_b: String,
}

/// A's address.
pub const ADDR_A: &str = "10.77.0.1";
/// B's address.
pub const ADDR_B: &str = "10.77.0.2";

impl Pair {
    /// Makes the pair (named after `tag` and this process): needs root and iproute2
    /// ([`crate::peers::IPROUTE2`]).
    pub fn new(tag: &str) -> Result<Pair, String> {
        crate::peers::require(&crate::peers::IPROUTE2).map_err(|e| e.to_string())?;
        let pid = std::process::id();
        let p = Pair {
            a: format!("hwgw-{tag}-{pid}-a"),
            b: format!("hwgw-{tag}-{pid}-b"),
            // Interface names have at most 15 bytes.
            veth_a: format!("hv{}a", pid % 1_000_000_000),
            veth_b: format!("hv{}b", pid % 1_000_000_000),
        };
        // Dropped on error: removes whatever was made.
        ip(&["netns", "add", &p.a])?;
        ip(&["netns", "add", &p.b])?;
        ip(&[
            "link", "add", &p.veth_a, "netns", &p.a, "type", "veth", "peer", "name", &p.veth_b,
            "netns", &p.b,
        ])?;
        for (ns, dev, addr) in [(&p.a, &p.veth_a, ADDR_A), (&p.b, &p.veth_b, ADDR_B)] {
            ip(&["-n", ns, "addr", "add", &format!("{addr}/24"), "dev", dev])?;
            ip(&["-n", ns, "link", "set", dev, "up"])?;
            ip(&["-n", ns, "link", "set", "lo", "up"])?;
        }
        Ok(p)
    }

    /// The command prefix that runs a program in namespace `ns`.
    pub fn exec(ns: &str) -> [&str; 4] {
        ["ip", "netns", "exec", ns]
    }

    /// Cuts (`up = false`) or restores the link, at both ends.
    pub fn link(&self, up: bool) -> Result<(), String> {
        let state = if up { "up" } else { "down" };
        ip(&["-n", &self.a, "link", "set", &self.veth_a, state])?;
        ip(&["-n", &self.b, "link", "set", &self.veth_b, state])
    }
}

impl Drop for Pair {
    fn drop(&mut self) {
        // The veth pair goes with its namespaces.
        let _ = ip(&["netns", "del", &self.a]);
        let _ = ip(&["netns", "del", &self.b]);
    }
}
