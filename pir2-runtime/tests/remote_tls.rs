//! The remote channel over mutual TLS on 127.0.0.1 with certificates generated here: a client
//! holding a certificate of the user's CA talks to `serve_policy`; a client whose certificate
//! comes from another CA, or one without TLS, is refused. Bounded: a few seconds.
#![cfg(feature = "remote")]

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pir2_runtime::remote::{
    serve_policy, Link, PolicyServerConfig, RemoteModel, RemoteModelConfig, TlsFiles,
};
use pir2_runtime::testing::SleepyModel;
use pir2_runtime::{ModelInput, SlowInput, VelocityModel};
use rcgen::{BasicConstraints, Certificate, CertificateParams, DnType, IsCa, KeyPair};

struct Ca {
    cert: Certificate,
    key: KeyPair,
    pem: PathBuf,
}

fn ca(dir: &Path, name: &str) -> Ca {
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    p.distinguished_name.push(DnType::CommonName, name);
    let key = KeyPair::generate().unwrap();
    let cert = p.self_signed(&key).unwrap();
    let pem = dir.join(format!("{name}.pem"));
    std::fs::write(&pem, cert.pem()).unwrap();
    Ca { cert, key, pem }
}

/// A certificate for 127.0.0.1 / localhost signed by `issuer`, trusting `trust`.
fn leaf(dir: &Path, name: &str, issuer: &Ca, trust: &Ca) -> TlsFiles {
    leaf_for(dir, name, &["localhost", "127.0.0.1"], issuer, trust)
}

/// A certificate for `hosts` signed by `issuer`, trusting `trust`.
fn leaf_for(dir: &Path, name: &str, hosts: &[&str], issuer: &Ca, trust: &Ca) -> TlsFiles {
    let hosts: Vec<String> = hosts.iter().map(|h| h.to_string()).collect();
    let mut p = CertificateParams::new(hosts).unwrap();
    p.distinguished_name.push(DnType::CommonName, name);
    let key = KeyPair::generate().unwrap();
    let cert = p.signed_by(&key, &issuer.cert, &issuer.key).unwrap();
    let (c, k) = (
        dir.join(format!("{name}.crt")),
        dir.join(format!("{name}.key")),
    );
    std::fs::write(&c, cert.pem()).unwrap();
    std::fs::write(&k, key.serialize_pem()).unwrap();
    TlsFiles {
        ca: trust.pem.clone(),
        cert: c,
        key: k,
    }
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

fn client(link: Link) -> pir2_runtime::remote::Result<RemoteModel> {
    RemoteModel::connect(RemoteModelConfig {
        link: Link {
            retry: Duration::from_millis(20),
            ..link
        },
        key: "test/tls".into(),
        timeout: Duration::from_millis(300),
        max_failed_calls: 3,
        connect_timeout: Duration::from_secs(2),
    })
}

fn scratch() -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "pir2-tls-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn tls_server(port: u16, files: TlsFiles, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    let cfg = PolicyServerConfig {
        link: Link::listen(format!("tls/127.0.0.1:{port}")).with_tls(files),
        key: "test/tls".into(),
        ..Default::default()
    };
    std::thread::spawn(move || {
        serve_policy(
            SleepyModel {
                latency: Duration::ZERO,
            },
            &cfg,
            stop,
        )
        .unwrap()
    })
}

/// A TLS failure is one error naming TLS and what was wrong (before: "no answer"): a file
/// that cannot be read or is not PEM is named before any session opens; a handshake the
/// server's certificate fails (another CA, another host name) is reported as a failed TLS
/// handshake with the usual causes.
#[test]
fn tls_failures_are_named_as_such() {
    let dir = scratch();
    let user_ca = ca(&dir, "user-ca");
    let other_ca = ca(&dir, "other-ca");
    let good = leaf(&dir, "robot", &user_ca, &user_ca);
    let (port, named_port) = (free_port(), free_port());
    let stop = Arc::new(AtomicBool::new(false));
    let servers = [
        tls_server(port, leaf(&dir, "server", &user_ca, &user_ca), stop.clone()),
        // A certificate of the right CA for another host than the one dialled.
        tls_server(
            named_port,
            leaf_for(
                &dir,
                "elsewhere",
                &["elsewhere.example"],
                &user_ca,
                &user_ca,
            ),
            stop.clone(),
        ),
    ];
    let ep = format!("tls/127.0.0.1:{port}");
    let err = |files: TlsFiles, ep: &str| {
        client(Link::connect(ep).with_tls(files))
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };

    let garbage = dir.join("garbage.crt");
    std::fs::write(&garbage, "this is not a certificate\n").unwrap();
    let e = err(
        TlsFiles {
            cert: garbage.clone(),
            ..good.clone()
        },
        &ep,
    );
    assert!(
        e.starts_with("TLS: the certificate file")
            && e.contains(&garbage.display().to_string())
            && e.contains("not a PEM certificate"),
        "{e}"
    );
    let missing = dir.join("missing.key");
    let e = err(
        TlsFiles {
            key: missing.clone(),
            ..good.clone()
        },
        &ep,
    );
    assert!(
        e.starts_with("TLS: the private key file")
            && e.contains(&missing.display().to_string())
            && e.contains("cannot be read"),
        "{e}"
    );
    // Trusts another CA than the one that signed the server's certificate.
    let wrong_ca = leaf(&dir, "robot-other-ca", &user_ca, &other_ca);
    let e = err(wrong_ca, &ep);
    assert!(
        e.contains("TLS: the TLS handshake with `tls/127.0.0.1:") && e.contains("not signed by"),
        "{e}"
    );
    let e = err(good.clone(), &format!("tls/127.0.0.1:{named_port}"));
    assert!(
        e.contains("TLS handshake") && e.contains("does not name the host"),
        "{e}"
    );
    // The right files against the right server still work.
    assert!(client(Link::connect(ep).with_tls(good)).is_ok());

    stop.store(true, Ordering::SeqCst);
    for s in servers {
        s.join().unwrap();
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn mutual_tls_serves_the_right_client_and_refuses_the_others() {
    let dir = scratch();
    let user_ca = ca(&dir, "user-ca");
    let rogue_ca = ca(&dir, "rogue-ca");
    let server_files = leaf(&dir, "server", &user_ca, &user_ca);
    let good = leaf(&dir, "robot", &user_ca, &user_ca);
    // Trusts the right CA (would accept the server) but holds a certificate of another CA.
    let rogue = leaf(&dir, "rogue", &rogue_ca, &user_ca);

    let port = free_port();
    let ep = format!("tls/127.0.0.1:{port}");
    let stop = Arc::new(AtomicBool::new(false));
    let cfg = PolicyServerConfig {
        link: Link::listen(ep.clone()).with_tls(server_files),
        key: "test/tls".into(),
        ..Default::default()
    };
    let s = stop.clone();
    let server = std::thread::spawn(move || {
        serve_policy(
            SleepyModel {
                latency: Duration::ZERO,
            },
            &cfg,
            s,
        )
    });

    let mut model = client(Link::connect(ep.clone()).with_tls(good)).expect("the right client");
    let x = vec![0.25f32; 4 * 2];
    let (tau, obs, d_vis) = (vec![0.0f32; 4], vec![0.0f32; 3], [0u32]);
    let input = ModelInput {
        batch: 1,
        horizon: 4,
        action_dim: 2,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: 1,
        fast_dim: 3,
        slow: SlowInput::None,
        d_vis: &d_vis,
    };
    let mut out = vec![0.0f32; 8];
    model.velocity(&input, &mut out).unwrap();
    assert!(out.iter().all(|&v| v == -0.25));

    let t0 = Instant::now();
    assert!(
        client(Link::connect(ep.clone()).with_tls(rogue)).is_err(),
        "a client certificate of another CA was accepted"
    );
    assert!(
        client(Link::connect(format!("tcp/127.0.0.1:{port}"))).is_err(),
        "a plain TCP client was accepted"
    );
    assert!(t0.elapsed() < Duration::from_secs(10));

    stop.store(true, Ordering::SeqCst);
    server.join().unwrap().unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn listening_beyond_loopback_needs_tls_or_an_explicit_insecure() {
    let tls = TlsFiles {
        ca: "ca.pem".into(),
        cert: "c.pem".into(),
        key: "k.pem".into(),
    };
    assert!(Link::listen("tcp/0.0.0.0:7447")
        .check_exposure(false)
        .is_err());
    assert!(Link::listen("tcp/10.0.0.2:7447")
        .check_exposure(false)
        .is_err());
    assert!(Link::listen("tcp/0.0.0.0:7447")
        .check_exposure(true)
        .is_ok());
    assert!(Link::listen("tcp/127.0.0.1:7447")
        .check_exposure(false)
        .is_ok());
    assert!(Link::listen("tcp/[::1]:7447").check_exposure(false).is_ok());
    assert!(Link::listen("unixsock-stream/tmp/p.sock")
        .check_exposure(false)
        .is_ok());
    assert!(Link::listen("tls/0.0.0.0:7447")
        .check_exposure(false)
        .is_err());
    assert!(Link::listen("tls/0.0.0.0:7447")
        .with_tls(tls.clone())
        .check_exposure(false)
        .is_ok());
}

/// The client side too: a robot connecting in plain TCP to another host is refused unless
/// `insecure` (before: `run --remote-policy tcp/10.0.0.2:7447` connected and used whatever
/// answered there).
#[test]
fn connecting_beyond_loopback_needs_tls_or_an_explicit_insecure() {
    let tls = TlsFiles {
        ca: "ca.pem".into(),
        cert: "c.pem".into(),
        key: "k.pem".into(),
    };
    let e = Link::connect("tcp/10.0.0.2:7447")
        .check_exposure(false)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("refusing to connect to `tcp/10.0.0.2:7447`"),
        "{e}"
    );
    assert!(Link::connect("tcp/10.0.0.2:7447")
        .check_exposure(true)
        .is_ok());
    assert!(Link::connect("tcp/127.0.0.1:7447")
        .check_exposure(false)
        .is_ok());
    assert!(Link::connect("tcp/localhost:7447")
        .check_exposure(false)
        .is_ok());
    assert!(Link::connect("tls/10.0.0.2:7447")
        .check_exposure(false)
        .is_err());
    assert!(Link::connect("tls/10.0.0.2:7447")
        .with_tls(tls)
        .check_exposure(false)
        .is_ok());
}
