//! The rig itself, inside its guest: the right kernel, the host's files, a writable
//! overlay, modules on demand, and can-utils talking over a real vcan.

use kernel_rig::{Failed, Trial, sh};

fn kernel_is_the_rigs() -> Result<(), Failed> {
    let want = std::fs::read_to_string(kernel_rig::rig_dir().join("kernel/version"))?;
    let got = sh("uname -r")?;
    if got.trim() != want.trim() {
        return Err(format!("guest kernel {got:?}, rig kernel {want:?}").into());
    }
    Ok(())
}

fn host_root_is_shared_under_a_writable_overlay() -> Result<(), Failed> {
    // This very test source is visible at its host path...
    let me = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/guest.rs");
    std::fs::metadata(me).map_err(|e| format!("{me}: {e}"))?;
    // ...and writes land in the guest's overlay, not on the host.
    let probe = "/etc/kernel-rig-overlay-probe";
    std::fs::write(probe, b"x").map_err(|e| format!("{probe}: {e}"))?;
    Ok(())
}

fn vcan_frames_cross_between_can_utils() -> Result<(), Failed> {
    sh("ip link add rigtest0 type vcan && ip link set rigtest0 up")?;
    // The capture is listening when it returns: the frame cannot come too early.
    let dump = testkit::Candump::start(&["-n", "1", "-T", "5000", "rigtest0"])?;
    sh("cansend rigtest0 123#DEADBEEF")?;
    let frames = dump.frames()?;
    if frames.iter().map(|(_, f)| f.as_str()).ne(["123#DEADBEEF"]) {
        return Err(format!("candump saw {frames:?}").into());
    }
    Ok(())
}

fn main() -> std::process::ExitCode {
    let rig = testkit::rig::vcan();
    kernel_rig::harness(
        &rig,
        vec![
            Trial::test("kernel_is_the_rigs", kernel_is_the_rigs),
            Trial::test(
                "host_root_is_shared_under_a_writable_overlay",
                host_root_is_shared_under_a_writable_overlay,
            ),
            Trial::test(
                "vcan_frames_cross_between_can_utils",
                vcan_frames_cross_between_can_utils,
            ),
        ],
    )
}
