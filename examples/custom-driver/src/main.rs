//! `hwgw` with the `loopback` driver added.

fn main() -> std::process::ExitCode {
    hwgw::cli::main(hwgw_example_driver::types())
}
