//! hwgw's Debian package under a real systemd: before the kernel rig boots (with systemd
//! as PID 1), the package is built from the binary cargo built for this test
//! (`packaging/build-deb.sh`: cargo-deb, manual pages and completions generated from the
//! CLI), twice — `…-1` and a higher `…-2` — and lintian checks it. In the guest an
//! operator installs it with apt (its dependencies resolved offline): systemd-sysusers
//! makes the user, udev applies the rules, the unit starts the packaged demo (Type=notify:
//! READY and STATUS); an operator of group hwgw (alice) talks to it over
//! /run/hwgw/hwgw.sock while a user outside the group (mallory) cannot; `man hwgw` renders
//! and bash completes `hwgw st`. With the operator's own deployment in place of the demo:
//! logs land in the journal with their fields, a component stalled on purpose starves the
//! watchdog and systemd restarts the gateway, `systemctl stop` leaves the CAN outputs'
//! safe frames on a vcan, udev gives group hwgw the device nodes its rules name. Then the
//! package's life: an upgrade while an output is held stops the old gateway with its
//! outputs safe and runs the new one; a deployment hwgw refuses leaves the unit failed
//! with the errors in the journal and nothing started; remove leaves only the conffile,
//! purge nothing but the system user.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use std::time::Duration;
use testkit::peers::{BASH_COMPLETION, MAN_DB};
use testkit::{Candump, wait_for};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const REPO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// What the gateway logs when it stops with sim0's analog output at its safe value.
const SIM0_SAFE: &str = "card \"sim0\" outputs at stop: analog [0],";

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

/// What systemd says of the unit, and its journal: told with a trial's failure.
fn unit_story() -> String {
    sh(
        "systemctl show -p SubState -p NRestarts -p Result -p ExecMainStatus hwgw; \
        systemctl list-jobs --no-pager; journalctl -u hwgw -o short-monotonic --no-pager -n 60",
    )
    .unwrap_or_else(|e| e.message().unwrap_or_default().to_string())
}

fn active() -> bool {
    unit("ActiveState").is_ok_and(|s| s == "active")
}

/// `apt-get ARGS` as an operator runs it, offline: what the package needs must already be
/// on the machine (the guest has no network interface but lo), so apt sees no package
/// lists, only what dpkg has installed — the host's 26 MB of lists, parsed again by each
/// apt-get in the emulated guest (a container image keeps no cache of them), cost 80–110 s
/// a call. Its output, or an error with it. (`--no-download` would say so too, but apt 2.6
/// then refuses a local .deb: "Pathname to install is not absolute".) It waits up to 120 s
/// for dpkg's lock, as an operator would.
fn apt(args: &str) -> Result<String, Failed> {
    let out = sh(&format!(
        "{{ mkdir -p {OFFLINE}/lists/partial {OFFLINE}/sources.list.d \
         && : > {OFFLINE}/sources.list \
         && DEBIAN_FRONTEND=noninteractive timeout 300 apt-get -y -q --no-install-recommends \
         -o Dir::Etc::SourceList={OFFLINE}/sources.list \
         -o Dir::Etc::SourceParts={OFFLINE}/sources.list.d -o Dir::State::Lists={OFFLINE}/lists \
         -o DPkg::Lock::Timeout=120 {args}; }} 2>&1; echo rc=$?"
    ))?;
    match out.trim_end().strip_suffix("rc=0") {
        Some(text) => Ok(text.to_string()),
        None => Err(format!("apt-get {args}:\n{out}").into()),
    }
}

/// Where [`apt`] finds no sources and no lists.
const OFFLINE: &str = "/tmp/apt-offline";

/// The package's status and version in dpkg's database ("" when dpkg knows it no more).
fn package() -> Result<String, Failed> {
    Ok(
        sh("dpkg-query -W -f='${Status} ${Version}' hwgw 2>/dev/null || true")?
            .trim()
            .to_string(),
    )
}

/// A cursor at the journal's end: [`journal_since`] gives what came after it.
fn journal_cursor() -> Result<String, Failed> {
    let out = sh("journalctl -n 0 --show-cursor --no-pager")?;
    out.lines()
        .find_map(|l| l.strip_prefix("-- cursor: "))
        .map(str::to_string)
        .ok_or_else(|| format!("no cursor from journalctl: {out:?}").into())
}

/// The unit's journal entries after `cursor`, as (PID, message).
fn journal_since(cursor: &str) -> Result<Vec<(String, String)>, Failed> {
    let json = sh(&format!(
        "journalctl -u hwgw -o json --no-pager --after-cursor='{cursor}'"
    ))?;
    Ok(json
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .map(|e| {
            (
                e["_PID"].as_str().unwrap_or_default().to_string(),
                e["MESSAGE"].as_str().unwrap_or_default().to_string(),
            )
        })
        .collect())
}

/// The files (not directories) dpkg lists for the package.
fn package_files() -> Result<Vec<String>, Failed> {
    Ok(sh("dpkg-query -L hwgw")?
        .lines()
        .filter(|f| !f.is_empty() && !std::path::Path::new(f).is_dir())
        .map(str::to_string)
        .collect())
}

fn exists(path: &str) -> bool {
    std::path::Path::new(path).symlink_metadata().is_ok()
}

fn lintian_finds_no_error_in_the_package() -> Result<(), Failed> {
    let report = testkit::deb::lintian_report()?;
    println!("lintian on {}:\n{report}", testkit::deb::first()?.display());
    let errors: Vec<&str> = report.lines().filter(|l| l.starts_with("E:")).collect();
    if !errors.is_empty() {
        return Err(format!("lintian errors:\n{}", errors.join("\n")).into());
    }
    Ok(())
}

fn the_package_installs_with_apt_and_starts_the_demo() -> Result<(), Failed> {
    let deb = testkit::deb::first()?;
    // A container image's policy-rc.d (exit 101: start no service while the image is
    // built) is no part of an operator's machine; the guest runs the host's files.
    sh("rm -f /usr/sbin/policy-rc.d")?;
    // man-db's trigger would index every manual page of the host, minutes over 9p in the
    // emulated guest (`man hwgw` finds the page without the index).
    sh("rm -f /var/lib/man-db/auto-update")?;
    // The CAN card of the operator's deployment (later) needs its interface.
    sh("ip link add vcan0 type vcan && ip link set vcan0 up")?;
    apt(&format!("install {}", deb.display()))?;
    let status = package()?;
    if !status.starts_with("install ok installed ") || !status.ends_with("-1") {
        return Err(format!("dpkg says: {status:?}").into());
    }
    let user = sh("getent passwd hwgw")?;
    if !user.starts_with("hwgw:") {
        return Err(format!("the package made no user hwgw: {user:?}").into());
    }
    // Type=notify: the postinst's start returned once READY=1 came.
    let enabled = sh("systemctl is-enabled hwgw")?;
    let status = unit("StatusText")?;
    if !(enabled.trim() == "enabled"
        && active()
        && status.starts_with("running")
        && status.contains("/run/hwgw/hwgw.sock"))
    {
        return Err(format!(
            "enabled {enabled:?}, active {}, status {status:?}",
            unit("ActiveState")?
        )
        .into());
    }
    let sock = sh("stat -c '%U %G %a' /run/hwgw/hwgw.sock /run/hwgw")?;
    if sock.lines().collect::<Vec<_>>() != ["hwgw hwgw 660", "hwgw hwgw 750"] {
        return Err(format!("socket and directory: {sock:?}").into());
    }
    // The conffile is the demo, which runs with no hardware.
    sh(&format!("cmp /etc/hwgw/hwgw.toml {REPO}/config/demo.toml"))?;
    let conffiles = sh("dpkg-query -W -f='${Conffiles}' hwgw")?;
    if !conffiles.contains("/etc/hwgw/hwgw.toml") {
        return Err(format!("conffiles: {conffiles:?}").into());
    }
    let log = sh("journalctl -u hwgw --no-pager -o cat")?;
    if !log.contains("component \"follow\"") {
        return Err(format!("the demo did not start:\n{log}").into());
    }
    // The postinst had udev reload its rules and apply them to the nodes already there.
    sh("udevadm settle")?;
    let i2c = sh("stat -c '%G %a' /dev/i2c-0")?;
    if i2c.trim() != "hwgw 660" {
        return Err(format!("/dev/i2c-0 after the install: {i2c}").into());
    }
    Ok(())
}

fn an_operator_in_group_hwgw_is_served_and_an_outsider_is_not() -> Result<(), Failed> {
    sh("useradd -M -G hwgw alice && useradd -M mallory")?;
    let status = as_user("alice", "status")?;
    if !status.starts_with("health: ok") {
        return Err(format!("operator's hwgw status: {status}").into());
    }
    // The service may be between a stop and a start when mallory asks: a guest stalled for
    // the watchdog's 5 s (a loaded host emulating it) has systemd restart it, and its
    // socket is gone until it is back. Then the journal says why, and mallory asks again
    // once the service is active with its socket.
    for asked in 1..=3 {
        let refused = sh("runuser -u mallory -- /usr/bin/hwgw status 2>&1; echo rc=$?")?;
        if refused.contains("Permission denied") && refused.contains("rc=1") {
            return Ok(());
        }
        if !refused.contains("hwgw.sock: No such file or directory") {
            return Err(format!("an outsider was not refused: {refused}").into());
        }
        if asked == 3 {
            break;
        }
        let journal = sh("journalctl -u hwgw --no-pager -o short-monotonic | tail -n 25")?;
        eprintln!("the service's socket was gone when mallory asked; its journal:\n{journal}");
        wait_for(
            "hwgw active with its socket again",
            Duration::from_secs(60),
            || active() && exists("/run/hwgw/hwgw.sock"),
        )?;
    }
    Err("the service's socket was gone each of 3 times mallory asked".into())
}

fn man_renders_and_bash_completes_hwgw_st() -> Result<(), Failed> {
    let path = sh("man -w hwgw")?;
    if path.trim() != "/usr/share/man/man1/hwgw.1.gz" {
        return Err(format!("man -w hwgw: {path}").into());
    }
    // groff's warnings on stderr, the page on stdout.
    for (page, want) in [
        ("hwgw", ["hwgw-status(1)", "/etc/hwgw/hwgw.toml"]),
        ("hwgw-status", ["--plot", "--socket"]),
    ] {
        let out = sh(&format!(
            "MANWIDTH=100 man --warnings -P cat {page} 2>/tmp/man.err; cat /tmp/man.err >&2; \
             test ! -s /tmp/man.err"
        ))?;
        if !want.iter().all(|w| out.contains(w)) {
            return Err(format!("man {page} has no {want:?}:\n{out}").into());
        }
    }
    // bash-completion's loader finds the package's completion the first time hwgw is
    // completed, as in an interactive shell; then TAB after `hwgw st`.
    let script = [
        ". /usr/share/bash-completion/bash_completion",
        "_completion_loader hwgw",
        "f=$(complete -p hwgw | sed -n \"s/.* -F \\([^ ]*\\) .*/\\1/p\")",
        "COMP_WORDS=(hwgw st) COMP_CWORD=1 COMP_LINE=\"hwgw st\" COMP_POINT=7",
        "$f hwgw st hwgw",
        "printf \"%s\\n\" \"${COMPREPLY[@]}\"",
    ];
    let words = sh(&format!("bash -c '{}'", script.join("; ")))?;
    if words.split_whitespace().collect::<Vec<_>>() != ["status"] {
        return Err(format!("hwgw st<TAB> completes to {words:?}").into());
    }
    Ok(())
}

fn the_operators_deployment_replaces_the_demo() -> Result<(), Failed> {
    sh(&format!(
        "install -m 0644 {REPO}/gateway/tests/data/systemd.toml /etc/hwgw/hwgw.toml \
         && systemctl restart hwgw"
    ))?;
    if !active() {
        return Err(format!("after the restart: {}", unit("ActiveState")?).into());
    }
    as_user("alice", "set sim0.do bit1 true")?;
    wait_for(
        "the operator's write on the card",
        Duration::from_secs(10),
        || as_user("alice", "get sim0.di bit1").is_ok_and(|v| v.trim() == "true"),
    )?;
    Ok(())
}

/// `systemctl reload hwgw` (the unit's ExecReload, `hwgw reload`): a change to the CAN
/// card's section rebuilds that card alone — the sim card's output set before stays set,
/// its gateway the same process; a deployment with an error fails the reload, the errors
/// in the journal, and changes nothing.
fn systemctl_reload_rebuilds_only_what_changed() -> Result<(), Failed> {
    as_user("alice", "set sim0.do bit2 true")?;
    wait_for(
        "the operator's write on the card",
        Duration::from_secs(10),
        || as_user("alice", "get sim0.di bit2").is_ok_and(|v| v.trim() == "true"),
    )?;
    let pid = unit("MainPID")?;
    let cursor = journal_cursor()?;
    sh("cp /etc/hwgw/hwgw.toml /tmp/before-reload.toml \
        && sed -i 's/cycle_ms = 10/cycle_ms = 20/' /etc/hwgw/hwgw.toml \
        && systemctl reload hwgw")?;
    let log = journal_since(&cursor)?;
    let said = |text: &str| log.iter().any(|(_, m)| m.contains(text));
    if !said("card \"can\" rebuilt") || said("card \"sim0\"") {
        return Err(format!("the reload's journal:\n{log:#?}").into());
    }
    if unit("MainPID")? != pid || !active() {
        return Err(format!("the gateway restarted: {} was {pid}", unit("MainPID")?).into());
    }
    if as_user("alice", "get sim0.di bit2")?.trim() != "true" {
        return Err("the sim card's output moved at the reload".into());
    }
    // An error: the reload fails, says why, and nothing changes.
    let cursor = journal_cursor()?;
    sh(
        "printf '\\n[[component]]\\nname = \"x\"\\ntype = \"no-such-type\"\\nactivity = { type = \"non_periodic\" }\\n' >> /etc/hwgw/hwgw.toml",
    )?;
    let refused = sh("systemctl reload hwgw 2>&1; echo rc=$?")?;
    if refused.trim_end().ends_with("rc=0") {
        return Err(format!("a broken deployment reloaded: {refused}").into());
    }
    let log = journal_since(&cursor)?;
    if !log
        .iter()
        .any(|(_, m)| m.contains("unknown component type \"no-such-type\""))
    {
        return Err(format!("the errors are not in the journal:\n{log:#?}").into());
    }
    if unit("MainPID")? != pid || !active() {
        return Err(format!("after the refused reload: {}", unit("ActiveState")?).into());
    }
    sh("cp /tmp/before-reload.toml /etc/hwgw/hwgw.toml && systemctl reload hwgw")?;
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
        if !test.contains("/usr/lib/udev/rules.d/65-hwgw.rules") || !test.contains("GROUP") {
            return Err(format!("udevadm test {sys}:\n{test}").into());
        }
        let owner = sh(&format!("stat -c '%G %a' {node}"))?;
        if owner.trim() != "hwgw 660" {
            return Err(format!("{node}: {owner}").into());
        }
    }
    Ok(())
}

fn an_upgrade_stops_the_old_gateway_with_its_outputs_safe_and_runs_the_new_one()
-> Result<(), Failed> {
    sh("systemctl start hwgw")?;
    as_user("alice", "set sim0.ao ch0 3.5")?;
    // Read back through the card's 16-bit raw range: 3.49996…
    wait_for("the held output", Duration::from_secs(10), || {
        as_user("alice", "get sim0.ao ch0").is_ok_and(|v| {
            v.trim()
                .parse::<f64>()
                .is_ok_and(|v| (v - 3.5).abs() < 0.01)
        })
    })?;
    let old = unit("MainPID")?;
    let cursor = journal_cursor()?;
    apt(&format!("install {}", testkit::deb::upgrade()?.display()))?;
    let status = package()?;
    if !status.starts_with("install ok installed ") || !status.ends_with("-2") {
        return Err(format!("dpkg says after the upgrade: {status:?}").into());
    }
    let new = unit("MainPID")?;
    if !active() || new == old || new == "0" {
        return Err(format!("after the upgrade: {}, pid {new}", unit("ActiveState")?).into());
    }
    // The gateway that runs is the new package's file, not the old one's (deleted) image.
    let exe = sh(&format!(
        "readlink /proc/{new}/exe; stat -L -c %i /proc/{new}/exe /usr/bin/hwgw"
    ))?;
    let lines: Vec<&str> = exe.lines().collect();
    if !(lines.len() == 3 && lines[0] == "/usr/bin/hwgw" && lines[1] == lines[2]) {
        return Err(format!("process {new} runs {exe:?}").into());
    }
    let log = journal_since(&cursor)?;
    let stop = log
        .iter()
        .position(|(pid, m)| *pid == old && m.starts_with(SIM0_SAFE));
    let start = log
        .iter()
        .position(|(pid, m)| *pid == new && m.starts_with("running; control socket"));
    match (stop, start) {
        (Some(s), Some(r)) if s < r => {}
        _ => {
            return Err(format!(
                "the old gateway ({old}) did not stop safe before the new one ({new}) ran:\n{log:#?}"
            )
            .into());
        }
    }
    // The operator's deployment stays: the conffile is theirs.
    sh(&format!(
        "cmp /etc/hwgw/hwgw.toml {REPO}/gateway/tests/data/systemd.toml"
    ))?;
    Ok(())
}

fn a_refused_deployment_leaves_the_unit_failed_with_the_errors_in_the_journal() -> Result<(), Failed>
{
    sh("cp /etc/hwgw/hwgw.toml /tmp/deployment.toml \
        && printf '[[card]]\\nname = \"x\"\\ndriver = \"no-such-driver\"\\n' > /etc/hwgw/hwgw.toml")?;
    // What `hwgw check` says of it is what the journal must show.
    let errors = sh("/usr/bin/hwgw check /etc/hwgw/hwgw.toml 2>&1; echo rc=$?")?;
    let first = errors.lines().next().unwrap_or_default().to_string();
    if !errors.contains("rc=1") || first.is_empty() {
        return Err(format!("hwgw check: {errors}").into());
    }
    let cursor = journal_cursor()?;
    let restart = sh("systemctl restart hwgw 2>&1; echo rc=$?")?;
    if restart.trim_end().ends_with("rc=0") {
        return Err(format!("the restart succeeded: {restart}").into());
    }
    // Restart=on-failure tries again (each try passes through "failed"), until the start
    // limit leaves the unit failed for good — systemd says so in the unit's journal.
    wait_for(
        "the unit failed by the start limit",
        Duration::from_secs(120),
        || {
            journal_since(&cursor).is_ok_and(|log| {
                log.iter()
                    .any(|(_, m)| m.contains("Start request repeated too quickly"))
            }) && unit("ActiveState").is_ok_and(|s| s == "failed")
        },
    )?;
    let log = journal_since(&cursor)?;
    if !log.iter().any(|(_, m)| m.contains(&first)) {
        return Err(format!("{first:?} not in the journal:\n{log:#?}").into());
    }
    // Nothing was started: no process, no control socket.
    if unit("MainPID")? != "0" || exists("/run/hwgw/hwgw.sock") {
        return Err(format!("a gateway was left behind: {}", unit("MainPID")?).into());
    }
    sh("cp /tmp/deployment.toml /etc/hwgw/hwgw.toml \
        && systemctl reset-failed hwgw && systemctl start hwgw")?;
    if !active() {
        return Err(format!("the good deployment again: {}", unit("ActiveState")?).into());
    }
    Ok(())
}

fn remove_stops_the_gateway_and_leaves_only_the_conffile() -> Result<(), Failed> {
    let files = package_files()?;
    let old = unit("MainPID")?;
    let cursor = journal_cursor()?;
    apt("remove hwgw")?;
    let status = package()?;
    if !status.starts_with("deinstall ok config-files") {
        return Err(format!("dpkg says after remove: {status:?}").into());
    }
    if active() || sh("pgrep -x hwgw || true")?.trim() != "" {
        return Err(format!("hwgw still runs: {}", unit("ActiveState")?).into());
    }
    let log = journal_since(&cursor)?;
    if !log
        .iter()
        .any(|(pid, m)| *pid == old && m.starts_with("card \"can\" outputs at stop"))
    {
        return Err(format!("no stop with the outputs safe in the journal:\n{log:#?}").into());
    }
    let left: Vec<&String> = files.iter().filter(|f| exists(f)).collect();
    if left != ["/etc/hwgw/hwgw.toml"] {
        return Err(format!("left after remove: {left:?}").into());
    }
    Ok(())
}

fn purge_leaves_nothing_but_the_system_user() -> Result<(), Failed> {
    apt("purge hwgw")?;
    let status = package()?;
    if !status.is_empty() && !status.starts_with("unknown ok not-installed") {
        return Err(format!("dpkg says after purge: {status:?}").into());
    }
    let left = sh(
        "timeout 120 find /etc /usr/bin /usr/lib/systemd /usr/lib/udev /usr/lib/sysusers.d /usr/share/man \
         /usr/share/doc/hwgw /usr/share/bash-completion /usr/share/zsh /usr/share/fish \
         /var/lib/systemd /var/lib/dpkg/info /run/hwgw -name '*hwgw*' 2>/dev/null || true",
    )?;
    if !left.trim().is_empty() {
        return Err(format!("left after purge:\n{left}").into());
    }
    // Debian policy: a system user stays (files may still be owned by it).
    sh("getent passwd hwgw")?;
    Ok(())
}

fn main() -> std::process::ExitCode {
    // Fourteen trials with two package installs under an emulated CPU: 387 s on a quiet
    // machine and 404 s beside a cold clippy (440 s quiet and 505-606 s beside a build
    // before its guest ran no generators), over the rig's default 600 s beside a cold one.
    let rig = testkit::rig::vcan()
        .timeout(Duration::from_secs(1200))
        .systemd()
        .module("i2c-dev")
        .setup("modprobe i2c-stub chip_addr=0x48")
        .tool("runuser", "util-linux")
        .tool("useradd", "passwd")
        .tool("apt-get", "apt")
        .tool("pgrep", "procps");
    let rig = testkit::rig::with_peer(rig, &MAN_DB);
    let rig = testkit::rig::with_peer(rig, &BASH_COMPLETION);
    // On the host, before the guest boots: the packages its trials install. Kept (and
    // locked) until the guest is done.
    let listing = std::env::args().any(|a| a == "--list");
    let _packages = if kernel_rig::in_guest() || listing {
        None
    } else {
        match testkit::deb::build(std::path::Path::new(REPO), std::path::Path::new(HWGW)) {
            Ok(built) => Some(built),
            Err(e) => {
                eprintln!("kernel_systemd: FAILED: cannot build the hwgw package: {e}");
                return std::process::ExitCode::FAILURE;
            }
        }
    };
    // A failure is told at once: libtest tells them all at the end, which a guest that
    // runs out of time never reaches.
    let t = |name: &'static str, f: fn() -> Result<(), Failed>| {
        Trial::test(name, move || {
            let started = std::time::Instant::now();
            let result = f();
            if let Err(e) = &result {
                eprintln!(
                    "{name}: FAILED after {:?}: {}\n{}",
                    started.elapsed(),
                    e.message().unwrap_or_default(),
                    unit_story()
                );
            }
            result
        })
    };
    kernel_rig::harness(
        &rig,
        vec![
            t(
                "a_lintian_finds_no_error_in_the_package",
                lintian_finds_no_error_in_the_package,
            ),
            t(
                "b_the_package_installs_with_apt_and_starts_the_demo",
                the_package_installs_with_apt_and_starts_the_demo,
            ),
            t(
                "c_an_operator_in_group_hwgw_is_served_and_an_outsider_is_not",
                an_operator_in_group_hwgw_is_served_and_an_outsider_is_not,
            ),
            t(
                "d_man_renders_and_bash_completes_hwgw_st",
                man_renders_and_bash_completes_hwgw_st,
            ),
            t(
                "e_the_operators_deployment_replaces_the_demo",
                the_operators_deployment_replaces_the_demo,
            ),
            t(
                "ea_systemctl_reload_rebuilds_only_what_changed",
                systemctl_reload_rebuilds_only_what_changed,
            ),
            t(
                "f_logs_land_in_the_journal_with_their_fields",
                logs_land_in_the_journal_with_their_fields,
            ),
            t(
                "g_a_stalled_component_starves_the_watchdog_and_systemd_restarts_hwgw",
                a_stalled_component_starves_the_watchdog_and_systemd_restarts_hwgw,
            ),
            t(
                "h_systemctl_stop_leaves_the_safe_frames_on_the_bus",
                systemctl_stop_leaves_the_safe_frames_on_the_bus,
            ),
            t(
                "i_udev_gives_group_hwgw_the_nodes_its_rules_name",
                udev_gives_group_hwgw_the_nodes_its_rules_name,
            ),
            t(
                "j_an_upgrade_stops_the_old_gateway_with_its_outputs_safe_and_runs_the_new_one",
                an_upgrade_stops_the_old_gateway_with_its_outputs_safe_and_runs_the_new_one,
            ),
            t(
                "k_a_refused_deployment_leaves_the_unit_failed_with_the_errors_in_the_journal",
                a_refused_deployment_leaves_the_unit_failed_with_the_errors_in_the_journal,
            ),
            t(
                "l_remove_stops_the_gateway_and_leaves_only_the_conffile",
                remove_stops_the_gateway_and_leaves_only_the_conffile,
            ),
            t(
                "m_purge_leaves_nothing_but_the_system_user",
                purge_leaves_nothing_but_the_system_user,
            ),
        ],
    )
}
