//! Locking a mutex whose data stays consistent across a panic.
//!
//! The runtime guards plain lists, samples and handles with mutexes; none of them can be
//! left half-updated by a panicking holder, so a poisoned lock is still usable and is taken
//! anyway. Never used on a real-time path.

use std::sync::{Mutex, MutexGuard};

/// Locks `m`, taking the data of a poisoned lock as it is.
pub fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}
