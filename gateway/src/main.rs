//! `hwgw`: run a deployment, check one, or talk to a running gateway.

fn main() -> std::process::ExitCode {
    hwgw::cli::main(hwgw::types::Types::builtin())
}
