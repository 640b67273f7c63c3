//! What hwgw's tests share, so no test file carries its own copy.
//!
//! - [`layout`]: checks of the source tree's shape (module cycles, function lengths).

pub mod layout;
