//! Waiting for a condition, with a deadline: never sleep and hope.

use std::time::{Duration, Instant};

/// How long [`wait_until`] waits before it fails a test: generous, since machines are
/// shared and noisy, and a passing test never waits that long.
pub const PATIENCE: Duration = Duration::from_secs(20);

/// Polls `f` every 2 ms until it holds; after `limit`, an error naming `what`.
pub fn wait_for(what: &str, limit: Duration, mut f: impl FnMut() -> bool) -> Result<(), String> {
    let end = Instant::now() + limit;
    while !f() {
        if Instant::now() > end {
            return Err(format!("{what}: not within {limit:?}"));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok(())
}

/// Polls `f` until it holds; panics naming `what` after [`PATIENCE`].
#[track_caller]
pub fn wait_until(what: &str, f: impl FnMut() -> bool) {
    if let Err(e) = wait_for(what, PATIENCE, f) {
        panic!("timed out: {e}");
    }
}

/// Polls `f` until it says yes, for [`PATIENCE`]; an error of `f` ends the wait and is
/// returned (a check that cannot be made is not a check that failed yet).
pub fn wait_ok(
    what: &str,
    mut f: impl FnMut() -> Result<bool, kernel_rig::Failed>,
) -> Result<(), kernel_rig::Failed> {
    let mut error = None;
    wait_for(what, PATIENCE, || match f() {
        Ok(done) => done,
        Err(e) => {
            error = Some(e);
            true
        }
    })?;
    error.map_or(Ok(()), Err)
}
