//! The shipped units under a real systemd: the kernel rig boots with systemd as PID 1 and
//! the tests install hwgw as an operator would — `systemd-sysusers` makes the user, the
//! unit starts it (Type=notify: READY and STATUS), an operator of group hwgw (alice) talks
//! to it over /run/hwgw/hwgw.sock while a user outside the group (mallory) cannot, logs land in the
//! journal with their fields, a component stalled on purpose starves the watchdog and
//! systemd restarts the gateway, `systemctl stop` leaves the CAN outputs' safe frames on a
//! vcan, and udev gives group hwgw the device nodes its rules name.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use std::time::Duration;
use testkit::{Candump, wait_for};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const REPO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// `hwgw ARGS` as `user` (the CLI's own socket search: no --socket).
fn as_user(user: &str, args: &str) -> Result<String, Failed> {
    sh(&format!("runuser -u {user} -- /usr/bin/hwgw {args} 2>&1"))
}

/// A property of the unit (`systemctl show -p NAME --value`).
fn unit(property: &str) -> Result<String, Failed> {
    Ok(sh(&format!("systemctl show -p {property} --value hwgw"))?
        .trim()
        .to_string())
}

fn active() -> bool {
    unit("ActiveState").is_ok_and(|s| s == "active")
}

fn installs_and_starts_as_an_operator_would() -> Result<(), Failed> {
    sh(&format!(
        // Stripped, as a package installs it: the debug build with Zenoh is over 300 MB,
        // more than the rig's RAM-backed overlay holds.
        "strip -o /usr/bin/hwgw {HWGW} && chmod 0755 /usr/bin/hwgw \
         && install -m 0644 {REPO}/systemd/hwgw.service /etc/systemd/system/ \
         && install -D -m 0644 {REPO}/systemd/hwgw.sysusers.conf /etc/sysusers.d/hwgw.conf \
         && systemd-sysusers \
         && install -D -m 0644 {REPO}/udev/65-hwgw.rules /etc/udev/rules.d/65-hwgw.rules \
         && udevadm control --reload \
         && install -D -m 0640 -g hwgw {REPO}/gateway/tests/data/systemd.toml /etc/hwgw/hwgw.toml \
         && ip link add vcan0 type vcan && ip link set vcan0 up \
         && systemctl daemon-reload"
    ))?;
    let user = sh("getent passwd hwgw")?;
    if !user.starts_with("hwgw:") {
        return Err(format!("systemd-sysusers made no user hwgw: {user:?}").into());
    }
    // Type=notify: `start` returns once READY=1 came.
    sh("systemctl start hwgw")?;
    let status = unit("StatusText")?;
    if !(active() && status.starts_with("running") && status.contains("/run/hwgw/hwgw.sock")) {
        return Err(format!("active {}, status {status:?}", unit("ActiveState")?).into());
    }
    let sock = sh("stat -c '%U %G %a' /run/hwgw/hwgw.sock /run/hwgw")?;
    if sock.lines().collect::<Vec<_>>() != ["hwgw hwgw 660", "hwgw hwgw 750"] {
        return Err(format!("socket and directory: {sock:?}").into());
    }
    Ok(())
}

fn an_operator_in_group_hwgw_is_served_and_an_outsider_is_not() -> Result<(), Failed> {
    sh("useradd -M -G hwgw alice && useradd -M mallory")?;
    let status = as_user("alice", "status")?;
    if !status.starts_with("health: ok") {
        return Err(format!("operator's hwgw status: {status}").into());
    }
    as_user("alice", "set sim0.do bit1 true")?;
    wait_for(
        "the operator's write on the card",
        Duration::from_secs(10),
        || as_user("alice", "get sim0.di bit1").is_ok_and(|v| v.trim() == "true"),
    )?;
    let refused = sh("runuser -u mallory -- /usr/bin/hwgw status 2>&1; echo rc=$?")?;
    if !(refused.contains("Permission denied") && refused.contains("rc=1")) {
        return Err(format!("an outsider was not refused: {refused}").into());
    }
    Ok(())
}

fn logs_land_in_the_journal_with_their_fields() -> Result<(), Failed> {
    let json = sh("journalctl -u hwgw -o json --no-pager")?;
    let line = json
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|e| {
            e["MESSAGE"]
                .as_str()
                .is_some_and(|m| m.starts_with("running; control socket /run/hwgw/hwgw.sock"))
        })
        .ok_or_else(|| format!("no start message in the journal:\n{json}"))?;
    for (field, want) in [
        ("_SYSTEMD_UNIT", "hwgw.service"),
        // tracing-journald: INFO is NOTICE (5).
        ("PRIORITY", "5"),
        ("TARGET", "hwgw::serve"),
    ] {
        if line[field] != want {
            return Err(format!("{field} is {} in {line}", line[field]).into());
        }
    }
    if !line["CODE_FILE"]
        .as_str()
        .is_some_and(|f| f.ends_with("serve.rs"))
    {
        return Err(format!("no CODE_FILE in {line}").into());
    }
    Ok(())
}

fn a_stalled_component_starves_the_watchdog_and_systemd_restarts_hwgw() -> Result<(), Failed> {
    let (pid, restarts) = (unit("MainPID")?, unit("NRestarts")?);
    as_user("alice", "lifecycle start stall")?;
    wait_for("the restart", Duration::from_secs(60), || {
        unit("NRestarts").is_ok_and(|n| n != restarts) && active()
    })?;
    let new_pid = unit("MainPID")?;
    if new_pid == pid {
        return Err(format!("still process {pid}").into());
    }
    let log = sh("journalctl -u hwgw --no-pager -o cat")?;
    for want in [
        "unhealthy, not feeding the watchdog: stall overruns its period",
        "Watchdog timeout",
        "outputs at stop",
    ] {
        if !log.contains(want) {
            return Err(format!("{want:?} not in the journal:\n{log}").into());
        }
    }
    Ok(())
}

fn systemctl_stop_leaves_the_safe_frames_on_the_bus() -> Result<(), Failed> {
    as_user("alice", "set can.ao Setpoint 12.5")?;
    let live = Candump::start(&["-n", "3", "-T", "5000", "vcan0,300:7FF"])?;
    let frames = live.frames()?;
    if frames.iter().any(|(_, f)| f != "300#7D00") {
        return Err(format!("while running: {frames:?}").into());
    }
    let dump = Candump::start(&["-n", "100000", "-T", "3000", "vcan0,300:7FF"])?;
    sh("systemctl stop hwgw")?;
    let frames = dump.frames()?;
    match frames.last() {
        Some((_, f)) if f == "300#0000" => Ok(()),
        _ => Err(format!(
            "the last frames were {:?}",
            &frames[frames.len().saturating_sub(3)..]
        )
        .into()),
    }
}

fn udev_gives_group_hwgw_the_nodes_its_rules_name() -> Result<(), Failed> {
    sh("udevadm trigger --settle --subsystem-match=i2c-dev --subsystem-match=misc")?;
    for (node, sys) in [
        ("/dev/i2c-0", "/sys/class/i2c-dev/i2c-0"),
        ("/dev/cpu_dma_latency", "/sys/class/misc/cpu_dma_latency"),
    ] {
        let test = sh(&format!("udevadm test {sys} 2>&1"))?;
        if !test.contains("65-hwgw.rules") || !test.contains("GROUP") {
            return Err(format!("udevadm test {sys}:\n{test}").into());
        }
        let owner = sh(&format!("stat -c '%G %a' {node}"))?;
        if owner.trim() != "hwgw 660" {
            return Err(format!("{node}: {owner}").into());
        }
    }
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan()
        .systemd()
        .module("i2c-dev")
        .setup("modprobe i2c-stub chip_addr=0x48")
        .tool("runuser", "util-linux")
        .tool("useradd", "passwd");
    let t = |name: &str, f: fn() -> Result<(), Failed>| Trial::test(name, f);
    kernel_rig::harness(
        &rig,
        vec![
            t(
                "a_installs_and_starts_as_an_operator_would",
                installs_and_starts_as_an_operator_would,
            ),
            t(
                "b_an_operator_in_group_hwgw_is_served_and_an_outsider_is_not",
                an_operator_in_group_hwgw_is_served_and_an_outsider_is_not,
            ),
            t(
                "c_logs_land_in_the_journal_with_their_fields",
                logs_land_in_the_journal_with_their_fields,
            ),
            t(
                "d_a_stalled_component_starves_the_watchdog_and_systemd_restarts_hwgw",
                a_stalled_component_starves_the_watchdog_and_systemd_restarts_hwgw,
            ),
            t(
                "e_systemctl_stop_leaves_the_safe_frames_on_the_bus",
                systemctl_stop_leaves_the_safe_frames_on_the_bus,
            ),
            t(
                "f_udev_gives_group_hwgw_the_nodes_its_rules_name",
                udev_gives_group_hwgw_the_nodes_its_rules_name,
            ),
        ],
    )
}
