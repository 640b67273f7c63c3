//! `[server.opcua]`'s security with an independent client (Python asyncua): Basic256Sha256
//! and Aes128_Sha256_RsaOaep signed and encrypted with a trusted client certificate;
//! an untrusted certificate refused (and put in the store's `rejected/`); users from a
//! file with roles — a read-only user's write refused BadUserAccessDenied, an operator's
//! taken, a wrong password refused and counted, no user name on the unsigned endpoint;
//! the server's certificate made on first start and kept on the next.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::os::unix::fs::PermissionsExt;
use testkit::certs::Certs;
use testkit::fixtures::SIM_CARD;
use testkit::opcua::UaClient;
use testkit::{Service, TempDir};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// A deployment with the sim card and a server whose store is `pki` and whose users are
/// `op` (operator) and `viewer`.
struct Setup {
    certs: Certs,
    dir: TempDir,
    url: String,
    text: String,
}

fn setup() -> Setup {
    let certs = Certs::make();
    certs.opcua_application("trusted", "urn:hwgw:test-client");
    certs.opcua_application("stranger", "urn:hwgw:test-client");
    let dir = TempDir::new("opcua-sec-store");
    let users = dir.path().join("users.toml");
    std::fs::write(
        &users,
        "[users.op]\npassword = \"op-secret\"\nrole = \"operator\"\n\
         [users.viewer]\npassword = \"view-secret\"\nrole = \"read_only\"\n",
    )
    .unwrap();
    std::fs::set_permissions(&users, std::fs::Permissions::from_mode(0o600)).unwrap();
    let port = testkit::free_port();
    let text = format!(
        "{SIM_CARD}\n[server.opcua]\nlisten = \"127.0.0.1:{port}\"\npki_dir = \"{}\"\n\
         users_file = \"{}\"\nallow_writes = true\nallow_calls = true\n",
        dir.path().join("pki").display(),
        users.display()
    );
    Setup {
        certs,
        dir,
        url: format!("opc.tcp://127.0.0.1:{port}/"),
        text,
    }
}

impl Setup {
    fn conf(&self, cert: &str, policy: &str, user: Option<(&str, &str)>) -> Value {
        let mut c = json!({
            "url": self.url,
            "policy": policy,
            "mode": "SignAndEncrypt",
            "cert": self.certs.path(&format!("{cert}.der")),
            "key": self.certs.path(&format!("{cert}-key.pem")),
            "app_uri": "urn:hwgw:test-client",
        });
        if let Some((u, p)) = user {
            c["user"] = json!(u);
            c["password"] = json!(p);
        }
        c
    }
}

fn write(c: &mut UaClient, value: f64) -> String {
    let a = c.ask(json!({"cmd": "write", "id": "sim0.ao.ch1", "type": "Double", "value": value}));
    a["status"].as_str().unwrap_or_else(|| panic!("{a}")).into()
}

fn get_ao1(svc: &Service) -> f64 {
    svc.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}))
        .as_f64()
        .unwrap_or(0.0)
}

#[test]
fn signed_and_encrypted_sessions_certificates_and_roles() {
    let s = setup();
    let svc = Service::run_text(HWGW, "opcua-security", &s.text).unwrap();
    let counters = || svc.server_status("server.opcua")["counters"].clone();

    // A certificate not yet trusted: refused, and kept in the store's rejected/; moved to
    // trusted/ (OPC UA's way: the administrator trusts what was refused), it is taken.
    let store = s.dir.path().join("pki");
    let refused = |cert: &str| {
        let e = UaClient::connect(&s.conf(cert, "Basic256Sha256", None))
            .err()
            .unwrap_or_else(|| panic!("{cert}: an untrusted certificate was taken"));
        assert!(e.contains("Bad"), "{e}");
        let files: Vec<_> = std::fs::read_dir(store.join("rejected"))
            .unwrap()
            .map(|f| f.unwrap().path())
            .collect();
        assert_eq!(files.len(), 1, "{files:?}");
        files[0].clone()
    };
    let file = refused("trusted");
    std::fs::rename(&file, store.join("trusted").join(file.file_name().unwrap())).unwrap();

    // A trusted certificate, both policies, signed and encrypted: anonymous reads, and
    // anonymous is read-only by default.
    for policy in ["Basic256Sha256", "Aes128Sha256RsaOaep"] {
        let mut c = UaClient::connect(&s.conf("trusted", policy, None))
            .unwrap_or_else(|e| panic!("{policy}: {e}"));
        let v = c.ask(json!({"cmd": "read", "ids": ["sim0.ai.ch0"]}));
        assert_eq!(v["values"][0]["status"], "Good", "{policy}: {v}");
        assert_eq!(write(&mut c, 1.0), "BadUserAccessDenied", "{policy}");
    }

    // Another certificate nobody trusted: refused.
    refused("stranger");

    // Users: the read-only one may not write (nor call), the operator may.
    let mut viewer =
        UaClient::connect(&s.conf("trusted", "Basic256Sha256", Some(("viewer", "view-secret"))))
            .unwrap();
    assert_eq!(write(&mut viewer, 2.0), "BadUserAccessDenied");
    let call = json!({"cmd": "call", "object": "component:sim0.ai", "method": "call:sim0.ai.read", "args": [["UInt32", 0]]});
    let a = viewer.ask(call.clone());
    assert!(a["status"].as_str().unwrap().starts_with("Bad"), "{a}");
    assert_ne!(get_ao1(&svc), 2.0, "a refused write wrote");
    let mut op =
        UaClient::connect(&s.conf("trusted", "Aes128Sha256RsaOaep", Some(("op", "op-secret"))))
            .unwrap();
    assert_eq!(write(&mut op, 2.0), "Good");
    testkit::wait_until("the operator's write", || get_ao1(&svc) == 2.0);
    assert_eq!(op.ask(call)["status"], "Good");

    // A wrong password: refused and counted. The unsigned endpoint offers no user-name
    // policy (the client finds none and does not send one).
    let before = counters()["logins_refused"].as_u64().unwrap();
    let e = UaClient::connect(&s.conf("trusted", "Basic256Sha256", Some(("op", "wrong"))))
        .err()
        .expect("a wrong password is refused");
    assert!(e.contains("BadIdentityTokenRejected"), "{e}");
    assert_eq!(counters()["logins_refused"].as_u64().unwrap(), before + 1);
    let open = json!({"url": s.url, "user": "op", "password": "op-secret"});
    assert!(
        UaClient::connect(&open).is_err(),
        "a user name taken without security"
    );

    // The certificate made on first start is kept on the next.
    let cert = s.dir.path().join("pki/own/cert.der");
    let made = std::fs::read(&cert).unwrap();
    let key = s.dir.path().join("pki/private/private.pem");
    assert_eq!(
        std::fs::metadata(&key).unwrap().permissions().mode() & 0o777,
        0o600
    );
    drop((viewer, op));
    let stopped = svc.terminate();
    assert!(stopped.status.success(), "{}", stopped.log);
    let svc = Service::run_text(HWGW, "opcua-security-again", &s.text).unwrap();
    assert_eq!(
        std::fs::read(&cert).unwrap(),
        made,
        "the certificate was made again"
    );
    let mut c = UaClient::connect(&s.conf("trusted", "Basic256Sha256", None)).unwrap();
    let v = c.ask(json!({"cmd": "read", "ids": ["sim0.ai.ch0"]}));
    assert_eq!(v["values"][0]["status"], "Good", "{v}");
    drop(svc);
}
