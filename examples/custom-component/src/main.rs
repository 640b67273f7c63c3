//! `hwgw` with the `threshold` component type added.

fn main() -> std::process::ExitCode {
    hwgw::cli::main(hwgw_example_custom::types())
}
