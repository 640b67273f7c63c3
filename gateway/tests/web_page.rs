//! `[server.web]` with the real binary: headless Chromium (Debian's `chromium` and
//! `chromium-driver`), driven by selenium from PyPI, loads the page, sees a live value
//! change within 2 s, reads the device table (equal to `hwgw status`), takes a screenshot
//! (kept in the target directory as the test's artifact); sets an output through the
//! page with the deployment's token, which `hwgw get` reads back, and is refused without
//! it. Without a browser: a read-only page refuses every write, and the page's headers
//! say what a browser needs (types, caching, a strict Content-Security-Policy).
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::path::PathBuf;
use std::process::Command;
use testkit::Service;
use testkit::http::{get, request};
use testkit::peers::{CHROMIUM, PYTHON, ensure};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DEMO: &str = include_str!("../../config/demo.toml");
const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/web_page.py");
const TOKEN: &str = "a-token-of-the-deployment-0123";

fn demo_with_web(writes: bool) -> String {
    format!(
        r#"{DEMO}
[server.web]
listen = "127.0.0.1:0"
ports = ["sim0.ai.ch0", "sim0.ai.ch3", "sim0.ao.ch1"]
allow_writes = {writes}
token = "{TOKEN}"
"#
    )
}

/// The screenshot's place: kept after the test, beside its binary.
fn artifact() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("web-page");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join("hwgw-web-page.png")
}

#[test]
fn chromium_shows_live_values_and_sets_an_output_with_the_token() {
    ensure(&CHROMIUM);
    let selenium = testkit::pypi::selenium().unwrap();
    let svc = Service::run_text(HWGW, "web-page", &demo_with_web(true)).unwrap();
    let addr = svc.server_address("server.web");
    let shot = artifact();
    let _ = std::fs::remove_file(&shot);
    let out = Command::new(PYTHON)
        .arg(SCRIPT)
        .args([
            &format!("http://{addr}/"),
            "sim0.ai.ch0",
            "sim0.ao.ch1",
            "2.75",
            TOKEN,
            &shot.to_string_lossy(),
        ])
        .env("PYTHONPATH", &selenium)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let seen: Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("the page: {seen}");

    let after = seen["live"]["after_s"].as_f64().unwrap();
    assert!(
        after < 2.0,
        "the live value changed only after {after} s: {seen}"
    );

    let status = svc.ok(json!({"cmd": "status"}));
    let want: Vec<Vec<String>> = status["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            ["name", "interface", "status"]
                .iter()
                .map(|k| d[k].as_str().unwrap().to_string())
                .collect()
        })
        .collect();
    let shown: Vec<Vec<String>> = serde_json::from_value(seen["devices"].clone()).unwrap();
    assert_eq!(shown, want);
    assert_eq!(seen["health"], "healthy");

    let png = std::fs::read(&shot).unwrap();
    assert!(png.starts_with(b"\x89PNG"), "{}", shot.display());
    eprintln!("screenshot: {}", shot.display());

    assert_eq!(seen["set_without_token"]["status"], 401, "{seen}");
    assert_eq!(seen["set"]["status"], 200, "{seen}");
    let read = svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}));
    let v = read.as_f64().unwrap();
    // The simulated output is 16 bits over ±10 V: a step of 0.3 mV.
    assert!(
        (v - 2.75).abs() < 1e-3,
        "set 2.75 through the page, read {v}"
    );

    let csp: Vec<&Value> = seen["console"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|m| m.as_str().unwrap().contains("Content Security Policy"))
        .collect();
    assert!(csp.is_empty(), "the page broke its own policy: {csp:?}");
}

#[test]
fn a_read_only_page_refuses_every_write_and_says_what_a_browser_needs() {
    let svc = Service::run_text(HWGW, "web-ro", &demo_with_web(false)).unwrap();
    let addr = svc.server_address("server.web");
    let before = svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}));
    let body = br#"{"component": "sim0.ao", "port": "ch1", "value": 3.5}"#;
    let auth = format!("Bearer {TOKEN}");
    let a = request(addr, "POST", "/api/set", &[("authorization", &auth)], body).unwrap();
    assert_eq!(a.status, 403, "{}", a.text());
    assert_eq!(
        svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"})),
        before
    );

    let page = get(addr, "/");
    assert_eq!(page.status, 200);
    assert_eq!(
        page.header("content-type"),
        Some("text/html; charset=utf-8")
    );
    let csp = page.header("content-security-policy").unwrap();
    assert!(csp.contains("default-src 'none'") && csp.contains("script-src 'self'"));
    assert!(!page.text().contains("<script>"), "no inline script");
    assert_eq!(page.header("x-content-type-options"), Some("nosniff"));
    for (path, kind) in [
        ("/app.js", "text/javascript; charset=utf-8"),
        ("/style.css", "text/css; charset=utf-8"),
        ("/api/status", "application/json"),
    ] {
        let a = get(addr, path);
        assert_eq!(a.status, 200, "{path}");
        assert_eq!(a.header("content-type"), Some(kind), "{path}");
        assert!(a.header("cache-control").is_some(), "{path}");
    }
    let status = get(addr, "/api/status").json();
    assert!(status["components"].as_array().unwrap().len() > 3);
}

#[test]
fn writes_with_the_token_reach_only_the_listed_inputs() {
    let svc = Service::run_text(HWGW, "web-writes", &demo_with_web(true)).unwrap();
    let addr = svc.server_address("server.web");
    let auth = format!("Bearer {TOKEN}");
    let set = |component: &str, port: &str, token: &str| {
        let body = json!({"component": component, "port": port, "value": 1.5}).to_string();
        let h = [
            ("authorization", token),
            ("content-type", "application/json"),
        ];
        request(addr, "POST", "/api/set", &h, body.as_bytes()).unwrap()
    };
    // Not listed (sim0.do.bit12, which nothing else drives), listed but an output
    // (sim0.ai.ch0), no token: refused, and the unlisted output left alone.
    let bit12 = || svc.ok(json!({"cmd": "get", "component": "sim0.do", "port": "bit12"}));
    let before = bit12();
    let mut h = vec![("authorization", auth.as_str())];
    h.push(("content-type", "application/json"));
    let body = json!({"component": "sim0.do", "port": "bit12", "value": true}).to_string();
    let a = request(addr, "POST", "/api/set", &h, body.as_bytes()).unwrap();
    assert_eq!(a.status, 403, "{}", a.text());
    assert_eq!(set("sim0.ai", "ch0", &auth).status, 403);
    assert_eq!(set("sim0.ao", "ch1", "Bearer wrong").status, 401);
    assert_eq!(bit12(), before);
    let a = set("sim0.ao", "ch1", &auth);
    assert_eq!(a.status, 200, "{}", a.text());
    let v = svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}));
    assert!((v.as_f64().unwrap() - 1.5).abs() < 1e-3, "{v}");
    assert!(
        svc.server_status("server.web")["counters"]["writes_refused"]
            .as_u64()
            .unwrap()
            >= 3
    );
}
