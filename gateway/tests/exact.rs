//! Values cross the control socket and the CLI bit for bit: floats that need all 17
//! significant digits (and the extremes of f64) are set through `hwgw set`, read back
//! through `hwgw get` and through the socket's JSON, and come back identical — serde_json
//! without `float_roundtrip` was one bit off (119.54499816894531 printed as
//! 119.54499816894533).

use serde_json::json;
use testkit::service::Service;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// Floats whose shortest round-trip text has 17 digits, or that sit at f64's edges.
const HARD: [f64; 8] = [
    119.544_998_168_945_31,
    0.300_000_000_000_000_04,
    -2.225_073_858_507_201_4e-308,
    5e-324,
    1.797_693_134_862_315_7e308,
    -1.797_693_134_862_315_7e308,
    9_007_199_254_740_993.0,
    0.1,
];

#[test]
fn floats_that_need_17_digits_come_back_bit_for_bit() {
    let svc = Service::start(HWGW, "exact", &[] as &[&str], &[]).unwrap_or_else(|e| panic!("{e}"));
    for v in HARD {
        let text = format!("{v:?}");
        let set = svc.cli(&["set", "follow", "property:offset", &text]);
        assert!(set.status.success(), "{text}: {set:?}");
        // Through the CLI: the same text (Rust's shortest round-trip form) and the same
        // bits.
        let got = svc
            .out(&["get", "follow", "property:offset"])
            .unwrap_or_else(|e| panic!("{e}"));
        let back: f64 = got.parse().unwrap_or_else(|e| panic!("{got:?}: {e}"));
        assert_eq!(back.to_bits(), v.to_bits(), "{text} came back as {got}");
        // Through the socket's JSON.
        let j = svc.ok(json!({"cmd": "get", "component": "follow", "property": "offset"}));
        assert_eq!(
            j.as_f64().map(f64::to_bits),
            Some(v.to_bits()),
            "{text} came back as {j}"
        );
        // Set through JSON, read through the CLI.
        svc.ok(json!({"cmd": "set", "component": "follow", "property": "gain", "value": v}));
        let got = svc
            .out(&["get", "follow", "property:gain"])
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            got.parse::<f64>().map(f64::to_bits).ok(),
            Some(v.to_bits()),
            "{text} came back as {got}"
        );
    }
    assert!(svc.terminate().status.success());
}
