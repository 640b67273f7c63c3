//! `hwgw` with J1939 cards, in the kernel rig: the real binary over a vcan with the
//! kernel's J1939 stack (`can-j1939.ko`), can-utils' `testj1939`, `j1939cat` and
//! `j1939acd` on the other end, candump watching the wire. Parameter groups are matched by
//! PGN whatever their source unless pinned, a 100-byte message arrives whole through the
//! kernel's transport and a 20-byte one leaves through it, and address claiming is seen
//! on the wire and against j1939acd: requests answered, contests won and lost as J1939-81
//! says, with and without the arbitrary-address capability.
#![allow(clippy::unwrap_used, reason = "test code")]

use kernel_rig::{Failed, Trial, sh};
use serde_json::Value;
use testkit::Service;
use testkit::wait::wait_ok;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DBC: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/j1939.dbc");

/// truck: not arbitrary-address capable, at 0x80. trailer: capable (bit 63), at 0x88.
const TRUCK: u64 = 0x00A0_0000_0000_0100;
const TRAILER: u64 = 0x80A0_0000_0000_0200;
/// j1939acd's NAME: higher than the truck's (it must give way).
const ACD: u64 = 0x00A0_0000_0000_0300;

fn deployment() -> String {
    format!(
        r#"
[[card]]
name = "truck"
driver = "socketcan"

[card.socketcan]
interface = "vcan3"
dbc = "{DBC}"
j1939 = {{ name = "{TRUCK:#x}", address = 0x80 }}
rx = [
    {{ message = "Prop10" }},
    {{ message = "Pinned21", source = 0x21 }},
    {{ message = "AnySource" }},
    {{ message = "Big" }},
]
tx = [{{ message = "Level", cycle_ms = 500 }}]

[[card]]
name = "trailer"
driver = "socketcan"

[card.socketcan]
interface = "vcan3"
dbc = "{DBC}"
j1939 = {{ name = "{TRAILER:#x}", address = 0x88 }}
tx = [{{ message = "TrailerStatus", cycle_ms = 100 }}]
"#
    )
}

/// The claim of card `card` from its counters: (state, address, won, lost, requests).
fn claim(gw: &Service, card: &str) -> Result<(String, Option<u64>, u64, u64, u64), Failed> {
    let c: Value = serde_json::from_str(&gw.out(&["call", card, "counters"])?)?;
    let j = &c["j1939"];
    let n = |k: &str| j[k].as_u64().unwrap_or(0);
    Ok((
        j["claim"]["state"].as_str().unwrap_or("").to_string(),
        j["claim"]["address"].as_u64(),
        n("won"),
        n("lost"),
        n("requests"),
    ))
}

/// Each received message of `card`: (name, received).
fn received(gw: &Service, card: &str) -> Result<Vec<(String, u64)>, Failed> {
    let c: Value = serde_json::from_str(&gw.out(&["call", card, "counters"])?)?;
    Ok(c["messages"]
        .as_array()
        .ok_or_else(|| format!("no messages in {c}"))?
        .iter()
        .map(|m| {
            (
                m["name"].as_str().unwrap_or("").to_string(),
                m["received"].as_u64().unwrap_or(0),
            )
        })
        .collect())
}

/// `hwgw call truck.ai read N` as the exact number.
fn read(gw: &Service, channel: u32) -> Result<f64, Failed> {
    let text = gw.out(&["call", "truck.ai", "read", &channel.to_string()])?;
    Ok(text
        .trim()
        .parse::<f64>()
        .map_err(|e| format!("read {channel}: {text:?}: {e}"))?)
}

/// A claim frame as candump writes it: `18EEFFsa#` and the NAME, little endian.
fn claim_frame(source: u8, name: u64) -> String {
    let data: String = name
        .to_le_bytes()
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect();
    format!("18EEFF{source:02X}#{data}")
}

/// The frames candump logged so far, as `ID#DATA`.
fn wire(log: &std::path::Path) -> Vec<String> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| l.split_whitespace().nth(2).map(str::to_string))
        .collect()
}

/// Waits until candump has logged `frame` at least `times` times.
fn seen(log: &std::path::Path, frame: &str, times: usize) -> Result<(), Failed> {
    wait_ok(&format!("{frame} on the wire"), || {
        Ok(wire(log).iter().filter(|f| *f == frame).count() >= times)
    })
}

/// A peer process, killed when dropped (a failed assertion included).
struct Killed(std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn matched_by_pgn_multi_packet_and_address_claims() -> Result<(), Failed> {
    sh("ip link add vcan3 type vcan && ip link set vcan3 up")?;
    let scratch = testkit::TempDir::new("j1939-wire");
    let log = scratch.path().join("candump.log");
    // On every CAN interface: a candump bound to vcan3 alone would end when the link
    // goes down below.
    let _dump = testkit::Candump::start_logging(&["any"], std::fs::File::create(&log)?)?;
    let gw = Service::run_text(HWGW, "j1939", &deployment())?;

    // Both nodes claim their addresses, and hold them once nobody contested in time.
    seen(&log, &claim_frame(0x80, TRUCK), 1)?;
    seen(&log, &claim_frame(0x88, TRAILER), 1)?;
    wait_ok("both addresses held", || {
        Ok(claim(&gw, "truck")?.0 == "claimed" && claim(&gw, "trailer")?.0 == "claimed")
    })?;
    assert_eq!(claim(&gw, "truck")?.1, Some(0x80));
    // Their cyclic groups go out from the claimed addresses (a 20-byte one as a BAM).
    seen(&log, "18FF5088#0000000000000000", 1)?;
    seen(&log, "18ECFF80#20140003FF40FF00", 1)?;

    // Matched by PGN: testj1939's 8 bytes (01 23 45 67 89 AB CD EF) from three sources,
    // one with another priority than the DBC's; a pinned source takes its own.
    for (from, pgn, prio) in [
        ("0x23", "0x0ff10", "-p3"),
        ("0x21", "0x0ff20", ""),
        ("0x22", "0x0ff20", ""),
    ] {
        sh(&format!("testj1939 -B -s {prio} vcan3:{from} :,{pgn}"))?;
    }
    wait_ok("three groups matched", || {
        let r = received(&gw, "truck")?;
        Ok(r.iter().filter(|(_, n)| *n == 1).count() == 3)
    })?;
    let r = received(&gw, "truck")?;
    assert_eq!(
        r,
        [("Prop10", 1), ("Pinned21", 1), ("AnySource", 1), ("Big", 0)]
            .map(|(n, c)| (n.to_string(), c))
    );
    assert_eq!(read(&gw, 0)?, f64::from(0x2301u16)); // A
    assert_eq!(read(&gw, 1)?, f64::from(0x23u8) * 0.5); // B
    assert_eq!(read(&gw, 2)?, f64::from(0xEFu8)); // C

    // 100 bytes from j1939cat to the truck's address: RTS/CTS, answered by the kernel for
    // hwgw's bound address, received whole.
    let big: Vec<u8> = (0..100u32).map(|i| (i * 37 + 11) as u8).collect();
    let file = scratch.path().join("big.bin");
    std::fs::write(&file, &big)?;
    // Debian 12's j1939cat (can-utils 2020.11) sends the message, then reads the
    // kernel's completion notice with a control buffer too small for this kernel's and
    // exits 1 ("recvmsg error notification: truncated"): its status says nothing of the
    // transfer, which hwgw's copy of the message below does.
    let cat = std::process::Command::new("j1939cat")
        .arg("-i")
        .arg(&file)
        .args(["vcan3:0x30", ":0x80,0x0ef00"])
        .output()?;
    let said = String::from_utf8_lossy(&cat.stderr);
    assert!(
        cat.status.success() || said.contains("recvmsg error notification"),
        "j1939cat: {said}"
    );
    wait_ok("the 100-byte message", || {
        Ok(received(&gw, "truck")?.contains(&("Big".to_string(), 1)))
    })?;
    let u32_at = |at: usize| f64::from(u32::from_le_bytes(big[at..at + 4].try_into().unwrap()));
    assert_eq!(read(&gw, 3)?, u32_at(0));
    assert_eq!(read(&gw, 4)?, u32_at(50));
    assert_eq!(read(&gw, 5)?, u32_at(96));
    assert!(
        wire(&log)
            .iter()
            .any(|f| f.starts_with("18EC8030#1064000F")),
        "an RTS"
    );

    // 20 bytes from hwgw, reassembled by j1939cat: Fill 12.5 % = raw 25 at byte 16.
    gw.out(&["set", "truck.ao", "Fill", "12.5"])?;
    let got = scratch.path().join("level.bin");
    wait_ok("j1939cat receives the Level group with Fill", || {
        sh(&format!(
            "timeout 1 j1939cat -r -B vcan3:0x90,0x0ff40 > {} || true",
            got.display()
        ))?;
        let b = std::fs::read(&got)?;
        Ok(b.chunks(20)
            .any(|m| m.len() == 20 && m[16] == 25 && m[17] == 0))
    })?;

    // j1939acd (a higher NAME, addresses 0x80-0x81) asks who is there: hwgw answers
    // with its claim, and j1939acd takes 0x81.
    let acd = std::process::Command::new("j1939acd")
        .args(["-r", "0x80-0x81", &format!("{ACD:016x}"), "vcan3"])
        .spawn()?;
    let _acd = Killed(acd);
    seen(&log, "18EAFFFE#00EE00", 1)?;
    seen(&log, &claim_frame(0x81, ACD), 1)?;
    assert!(claim(&gw, "truck")?.4 >= 1, "the request was answered");
    assert!(
        wire(&log)
            .iter()
            .filter(|f| **f == claim_frame(0x80, TRUCK))
            .count()
            >= 2
    );

    // The link goes down and comes back: the kernel forgot every claim, so both nodes
    // claim again, and the truck's group goes out again.
    let claims = |a, n| {
        wire(&log)
            .iter()
            .filter(|f| **f == claim_frame(a, n))
            .count()
    };
    let (truck_claims, trailer_claims) = (claims(0x80, TRUCK), claims(0x88, TRAILER));
    let bams = || {
        wire(&log)
            .iter()
            .filter(|f| f.starts_with("18ECFF80#"))
            .count()
    };
    sh("ip link set vcan3 down && ip link set vcan3 up")?;
    let after_bounce = bams();
    seen(&log, &claim_frame(0x80, TRUCK), truck_claims + 1)?;
    seen(&log, &claim_frame(0x88, TRAILER), trailer_claims + 1)?;
    wait_ok("the truck's group after the link came back", || {
        Ok(bams() > after_bounce)
    })?;

    // A higher NAME claims 0x80: the truck wins and claims again.
    let truck_claims = claims(0x80, TRUCK);
    sh(&format!(
        "cansend vcan3 {}",
        claim_frame(0x80, 0x0FA0_0000_0000_0001)
    ))?;
    seen(&log, &claim_frame(0x80, TRUCK), truck_claims + 1)?;
    wait_ok("the contest counted as won", || {
        Ok(claim(&gw, "truck")?.2 == 1)
    })?;

    // A lower NAME claims 0x80: the truck, not arbitrary-address capable, says it
    // cannot claim, stops sending, and refuses writes to its J1939 outputs.
    sh(&format!(
        "cansend vcan3 {}",
        claim_frame(0x80, 0x0000_0000_0000_0001)
    ))?;
    seen(&log, &claim_frame(0xFE, TRUCK), 1)?;
    wait_ok("truck without an address", || {
        Ok(claim(&gw, "truck")?.0 == "cannot_claim")
    })?;
    let tx = |gw: &Service| -> Result<u64, Failed> {
        let c: Value = serde_json::from_str(&gw.out(&["call", "truck", "counters"])?)?;
        Ok(c["tx_frames"].as_u64().unwrap_or(0) + c["tx_errors"].as_u64().unwrap_or(0))
    };
    let (before, tx_before) = (bams(), tx(&gw)?);
    let refused = gw.cli(&["call", "truck.ao", "write", "0", "20"]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success()
            && err.contains(&format!("NAME {TRUCK:#018x} holds no source address")),
        "{err}"
    );
    // The trailer's cyclic group keeps going meanwhile; the truck's does not.
    let trailer_frames = || {
        wire(&log)
            .iter()
            .filter(|f| f.starts_with("18FF5088#"))
            .count()
    };
    let t0 = trailer_frames();
    wait_ok("5 more trailer frames", || Ok(trailer_frames() >= t0 + 5))?;
    assert_eq!(
        tx(&gw)?,
        tx_before,
        "the truck tried to send after losing its address"
    );
    assert_eq!(bams(), before);

    // A lower NAME claims 0x88: the trailer, arbitrary-address capable, moves to the
    // first address of 128-247 nobody holds (0x80 and 0x81 are taken) and sends from it.
    sh(&format!(
        "cansend vcan3 {}",
        claim_frame(0x88, 0x0000_0000_0000_0002)
    ))?;
    seen(&log, &claim_frame(0x82, TRAILER), 1)?;
    seen(&log, "18FF5082#0000000000000000", 1)?;
    wait_ok("the trailer at 0x82", || {
        Ok(claim(&gw, "trailer")?.1 == Some(0x82))
    })?;
    assert_eq!(claim(&gw, "trailer")?.3, 1);

    // The kernel filtered the truck's socket to its PGNs: the trailer's groups, the BAM
    // frames and j1939acd's never reached it.
    let c: Value = serde_json::from_str(&gw.out(&["call", "truck", "counters"])?)?;
    assert_eq!(c["rx_unknown_id"], 0, "{c}");

    // At stop the trailer's safe value goes out at once; the truck's cannot, and the stop
    // says so (rather than waiting out the settle time for it, and making the trailer
    // late).
    let stopped = gw.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    assert!(
        stopped
            .log
            .contains("outputs not sent to vcan3's J1939 groups: bus error: J1939: NAME 0x00a0000000000100 holds no source address"),
        "{}",
        stopped.log
    );
    assert!(!stopped.log.contains("not in time"), "{}", stopped.log);
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan().module("can_j1939");
    kernel_rig::harness(
        &rig,
        vec![Trial::test(
            "matched_by_pgn_multi_packet_and_address_claims",
            matched_by_pgn_multi_packet_and_address_claims,
        )],
    )
}
