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
    let mut p =
        CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()]).unwrap();
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

#[test]
fn mutual_tls_serves_the_right_client_and_refuses_the_others() {
    let dir = std::env::temp_dir().join(format!(
        "pir2-tls-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos()
    ));
    std::fs::create_dir_all(&dir).unwrap();
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
