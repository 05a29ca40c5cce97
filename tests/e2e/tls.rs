//! TLS end to end: a CA and a server certificate made inside the test, a learner
//! process serving TLS with a token, and clients that trust the CA (or do not).

use crate::processes::serve;
use crate::saver;
use crate::temp_dir;
use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair};
use std::path::Path;
use std::process::{Command, Stdio};

/// Writes ca.pem, and cert.pem + key.pem for `localhost` and 127.0.0.1 signed by it;
/// also other-ca.pem, a CA that signed nothing here.
fn make_certs(dir: &Path) {
    let ca = |name: &str| {
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        p.distinguished_name.push(rcgen::DnType::CommonName, name);
        let key = KeyPair::generate().unwrap();
        let cert = p.self_signed(&key).unwrap();
        (cert, Issuer::new(p, key))
    };
    let (ca_cert, issuer) = ca("saver test CA");
    let (other, _) = ca("another CA");
    let key = KeyPair::generate().unwrap();
    let cert = CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()])
        .unwrap()
        .signed_by(&key, &issuer)
        .unwrap();
    std::fs::write(dir.join("ca.pem"), ca_cert.pem()).unwrap();
    std::fs::write(dir.join("other-ca.pem"), other.pem()).unwrap();
    std::fs::write(dir.join("cert.pem"), cert.pem()).unwrap();
    std::fs::write(dir.join("key.pem"), key.serialize_pem()).unwrap();
}

fn status(url: &str, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["status", "--learner", url, "--token", "tls-tok"];
    args.extend(extra);
    saver(&args)
}

#[test]
fn a_tls_learner_answers_clients_that_trust_its_ca_only() {
    let dir = temp_dir("tls");
    make_certs(&dir);
    let p = |f: &str| dir.join(f).display().to_string();
    let (cert, key, ca, other, out) = (
        p("cert.pem"),
        p("key.pem"),
        p("ca.pem"),
        p("other-ca.pem"),
        p("run"),
    );
    let (_learner, plain_url) = serve(&[
        "learner",
        "--listen",
        "127.0.0.1:0",
        "--tls-cert",
        &cert,
        "--tls-key",
        &key,
        "--token",
        "tls-tok",
        "--algo",
        "a2c",
        "--dim",
        "2",
        "--actors",
        "1",
        "--steps",
        "100000000",
        "--out",
        &out,
    ]);
    let url = plain_url.replace("http://", "https://");

    let ok = status(&url, &["--tls-ca", &ca]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(String::from_utf8_lossy(&ok.stdout).contains("algo a2c"));
    let health = saver(&["healthcheck", "--addr", &url, "--tls-ca", &ca]);
    assert!(
        health.status.success(),
        "{}",
        String::from_utf8_lossy(&health.stderr)
    );

    // No CA, a CA that did not sign the certificate, plain HTTP: all refused.
    let no_ca = status(&url, &[]);
    assert!(!no_ca.status.success());
    assert!(String::from_utf8_lossy(&no_ca.stderr).contains("--tls-ca"));
    assert!(!status(&url, &["--tls-ca", &other]).status.success());
    assert!(!status(&plain_url, &[]).status.success());

    // An actor over TLS registers and the learner trains on its rollouts.
    let mut actor = Command::new(env!("CARGO_BIN_EXE_saver"))
        .args([
            "actor",
            "--learner",
            &url,
            "--tls-ca",
            &ca,
            "--token",
            "tls-tok",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let w = saver(&[
        "weights",
        "--learner",
        &url,
        "--tls-ca",
        &ca,
        "--token",
        "tls-tok",
        "--min-version",
        "5",
    ]);
    let _ = actor.kill();
    let _ = actor.wait();
    assert!(w.status.success(), "{}", String::from_utf8_lossy(&w.stderr));
    assert!(String::from_utf8_lossy(&w.stdout).starts_with("version "));
    std::fs::remove_dir_all(dir).ok();
}
