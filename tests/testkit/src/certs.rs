//! Certificates for the TLS tests, made with openssl (Debian's `openssl`, installed when
//! missing): a CA with a server certificate for 127.0.0.1 and `localhost` and a client
//! certificate, and a client certificate of another CA — EC P-256 keys, X.509 v3 with the
//! extensions rustls asks for (a SAN for the server, CA:FALSE and the key usage of each).

use crate::TempDir;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A new EC P-256 key, unencrypted.
const EC_KEY: [&str; 5] = [
    "-newkey",
    "ec",
    "-pkeyopt",
    "ec_paramgen_curve:P-256",
    "-nodes",
];

/// Certificates for the TLS tests, made with openssl: a CA with a server certificate
/// for 127.0.0.1 and a client certificate, and a client certificate of another CA.
pub struct Certs {
    dir: TempDir,
}

impl Certs {
    /// Makes them in a directory of their own.
    pub fn make() -> Certs {
        crate::peers::ensure(&crate::peers::OPENSSL);
        static MADE: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = MADE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let certs = Certs {
            dir: TempDir::new(&format!("certs-{n}")),
        };
        for ca in ["ca", "other-ca"] {
            certs.openssl(
                &[
                    &["req", "-x509"][..],
                    &EC_KEY,
                    &[
                        "-keyout",
                        &format!("{ca}.key"),
                        "-out",
                        &format!("{ca}.pem"),
                        "-days",
                        "30",
                        "-subj",
                        &format!("/CN=hwgw test {ca}"),
                        "-addext",
                        "basicConstraints=critical,CA:TRUE",
                        "-addext",
                        "keyUsage=critical,keyCertSign,cRLSign",
                    ],
                ]
                .concat(),
            );
        }
        certs.leaf(
            "server",
            "ca",
            "serverAuth",
            "subjectAltName=IP:127.0.0.1,DNS:localhost\n",
        );
        certs.leaf("client", "ca", "clientAuth", "");
        certs.leaf("stranger", "other-ca", "clientAuth", "");
        certs
    }

    fn leaf(&self, name: &str, ca: &str, usage: &str, extra: &str) {
        let ext = self.path(&format!("{name}.ext"));
        let text = format!(
            "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage={usage}\n{extra}"
        );
        std::fs::write(&ext, text).unwrap_or_else(|e| panic!("{}: {e}", ext.display()));
        self.openssl(
            &[
                &["req"][..],
                &EC_KEY,
                &[
                    "-keyout",
                    &format!("{name}.key"),
                    "-out",
                    &format!("{name}.csr"),
                    "-subj",
                    &format!("/CN=hwgw test {name}"),
                ],
            ]
            .concat(),
        );
        self.openssl(&[
            "x509",
            "-req",
            "-in",
            &format!("{name}.csr"),
            "-CA",
            &format!("{ca}.pem"),
            "-CAkey",
            &format!("{ca}.key"),
            "-CAcreateserial",
            "-out",
            &format!("{name}.pem"),
            "-days",
            "30",
            "-extfile",
            &format!("{name}.ext"),
        ]);
    }

    fn openssl(&self, args: &[&str]) {
        let o = Command::new("openssl")
            .args(args)
            .current_dir(self.dir.path())
            .output()
            .unwrap_or_else(|e| panic!("cannot run openssl: {e}"));
        assert!(
            o.status.success(),
            "openssl {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr)
        );
    }

    /// A self-signed OPC UA application instance certificate `name.der` (DER) and its key
    /// `name-key.pem` (PEM: asyncua reads a key by its extension): RSA 2048, SHA-256, the application's URI `uri` and `localhost` in
    /// its SAN, the key usage and extended key usage (client and server) Part 6 names.
    pub fn opcua_application(&self, name: &str, uri: &str) -> (PathBuf, PathBuf) {
        self.openssl(&[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-sha256",
            "-keyout",
            &format!("{name}-key.pem"),
            "-outform",
            "DER",
            "-out",
            &format!("{name}.der"),
            "-days",
            "30",
            "-subj",
            &format!("/CN={name}/O=hwgw tests"),
            "-addext",
            &format!("subjectAltName=URI:{uri},DNS:localhost"),
            "-addext",
            "basicConstraints=critical,CA:FALSE",
            "-addext",
            "keyUsage=critical,digitalSignature,nonRepudiation,keyEncipherment,dataEncipherment,keyCertSign",
            "-addext",
            "extendedKeyUsage=serverAuth,clientAuth",
        ]);
        (
            self.path(&format!("{name}.der")),
            self.path(&format!("{name}-key.pem")),
        )
    }

    /// A file of theirs: `ca.pem`, `server.pem`, `client.key`, `stranger.pem`, ….
    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Their directory.
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }
}
