//! `pir2 serve policy` + `pir2 eval --remote` as two processes on 127.0.0.1: the remote eval
//! gives the local eval's result (the lock-step eval is deterministic), also when the
//! server is killed and restarted mid-run; without a server the eval fails with a clear
//! error. With feature `gr00t` too: `pir2 gr00t serve slow` (GR00T ONNX backbone) feeding
//! `pir2 gr00t run gr00t-xarm-xhand --emulate --remote-slow`, and `pir2 gr00t serve policy`
//! answering `pir2 gr00t run … --remote-policy`.
//!
//! One file on purpose: every test starts the same binary pair (server and client) with the
//! shared helpers at its top.
#![cfg(feature = "remote")]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use pir2_backends::candle::CandleModel;
use pir2_backends::config::{Config, MlpConfig, ModelConfig};
use pir2_backends::train::compute_stats;
use pir2_cli::study::ballplate as demo;
use pir2_cli::study::pipeline::Episodes;

mod common;
use common::Scratch;

/// A server process, killed when dropped.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[cfg(feature = "gr00t")]
/// Read the run's stderr until it says the warm-up is over (the robot is under control).
fn wait_under_control(err: &mut BufReader<std::process::ChildStderr>) {
    let mut lines = Vec::new();
    loop {
        let mut l = String::new();
        assert!(
            err.read_line(&mut l).unwrap() > 0,
            "the run ended in its warm-up: {lines:?}"
        );
        let done = l.contains("the robot is under control");
        lines.push(l);
        if done {
            return;
        }
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn pir2() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
}

fn serve(args: &[&str]) -> Server {
    Server(
        pir2()
            .arg("serve")
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn pir2 serve"),
    )
}

/// `pir2 gr00t serve ARGS…`.
#[cfg(feature = "gr00t")]
fn gr00t_serve(args: &[&str]) -> Server {
    Server(
        pir2()
            .args(["gr00t", "serve"])
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn pir2 gr00t serve"),
    )
}

/// An untrained (seeded) ball-plate MLP checkpoint: enough to compare remote and local.
fn checkpoint(dir: &Path) -> PathBuf {
    let eps = demo::collect(3, 0, false).unwrap();
    let spec = demo::spec();
    let stats = compute_stats(&Episodes(&eps), &spec).unwrap();
    let cfg = Config {
        spec,
        model: ModelConfig::Mlp(MlpConfig {
            width: 32,
            depth: 2,
            ..MlpConfig::default()
        }),
    };
    let ck = dir.join("ck");
    CandleModel::new(cfg, stats, 3).unwrap().save(&ck).unwrap();
    ck
}

const EVAL: [&str; 8] = [
    "eval",
    "--policy",
    "pir2",
    "--d0",
    "1,2",
    "--episodes",
    "10",
    "--seed",
];

/// `pir2 eval` (the lock-step ball-plate eval of [`EVAL`], seed 5) of `ck` run locally: the
/// result JSON it wrote in `dir`.
fn local_eval(dir: &Path, ck: &str) -> PathBuf {
    let json = dir.join("local.json");
    let out = pir2()
        .args(EVAL)
        .args(["5", "--checkpoint", ck, "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    json
}

/// The same eval against the policy server at `endpoint`, writing `json`, once it printed
/// that it is connected: the child, its stderr, and what it printed so far.
fn remote_eval_connected(
    ck: &str,
    endpoint: &str,
    json: &Path,
) -> (Child, BufReader<std::process::ChildStderr>, String) {
    let mut eval = pir2()
        .args(EVAL)
        .args(["5", "--checkpoint", ck, "--remote", endpoint, "--json"])
        .arg(json)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(eval.stderr.take().unwrap());
    let mut lines = String::new();
    while !lines.contains("connected to the policy server") {
        assert!(
            err.read_line(&mut lines).unwrap() > 0,
            "eval exited: {lines}"
        );
    }
    (eval, err, lines)
}

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// The counter `name` of the remote eval's report (`… timeouts N reconnects M …`).
fn counter(report: &str, name: &str) -> u64 {
    report
        .split(&format!("{name} "))
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no `{name}` in {report}"))
}

#[test]
fn eval_remote_matches_local_and_survives_a_server_restart() {
    let s = Scratch::new("eval-remote");
    let ck = checkpoint(s.path());
    let ck_s = ck.to_str().unwrap();
    let local_json = local_eval(s.path(), ck_s);

    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let server_args = ["policy", "--checkpoint", ck_s, "--listen", &endpoint];
    let server = serve(&server_args);
    let remote_json = s.path().join("remote.json");
    let t0 = Instant::now();
    // Once the eval is connected, kill the server for ~0.5 s mid-run.
    let (mut eval, mut err, lines) = remote_eval_connected(ck_s, &endpoint, &remote_json);
    std::thread::sleep(Duration::from_millis(300));
    drop(server);
    std::thread::sleep(Duration::from_millis(500));
    let still_running = eval.try_wait().unwrap().is_none();
    let _server = serve(&server_args);
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    let status = eval.wait().unwrap();
    eprintln!("remote eval {:?}: {lines} {rest}", t0.elapsed());
    assert!(status.success(), "{rest}");
    assert!(
        still_running,
        "the eval finished before the server was killed"
    );
    assert_eq!(read_json(&local_json), read_json(&remote_json));
    // The outage was seen, retried and counted.
    assert!(counter(&rest, "timeouts") >= 1, "{rest}");
    assert!(counter(&rest, "reconnects") >= 1, "{rest}");
}

#[test]
fn eval_remote_without_a_server_fails_cleanly() {
    let s = Scratch::new("eval-noserver");
    let ck = checkpoint(s.path());
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let t0 = Instant::now();
    let out = pir2()
        .args(EVAL)
        .args([
            "5",
            "--checkpoint",
            ck.to_str().unwrap(),
            "--remote",
            &endpoint,
        ])
        .args(["--connect-timeout", "1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains(&endpoint) && err.contains("pir2 serve policy") && err.contains("no answer"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(t0.elapsed() < Duration::from_secs(20));
}

/// A rogue Zenoh client joins the policy server mid-eval and answers every request with
/// finite, well-shaped, wrong velocities (the server routes the robot's requests to its
/// clients, so the rogue's replies reach the robot through the endpoint it dialled): the
/// eval uses only the replies of the server it shook hands with, counts the rogue's, and
/// gives the local result. A rogue already there at the handshake makes the client refuse
/// to pick a server (before: the first reply of anyone was used).
#[test]
fn a_rogue_client_of_the_policy_server_is_never_used() {
    use pir2_runtime::testing::rogue::{Attach, Rogue};

    let s = Scratch::new("eval-rogue");
    let ck = checkpoint(s.path());
    let ck_s = ck.to_str().unwrap();
    let local_json = local_eval(s.path(), ck_s);

    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _server = serve(&["policy", "--checkpoint", ck_s, "--listen", &endpoint]);
    let remote_json = s.path().join("remote.json");
    let (mut eval, mut err, mut lines) = remote_eval_connected(ck_s, &endpoint, &remote_json);
    let rogue =
        Rogue::policy_responder(&Attach::ClientOf(endpoint.clone()), "pir2/policy", 42.0).unwrap();
    std::io::Read::read_to_string(&mut err, &mut lines).unwrap();
    let status = eval.wait().unwrap();
    assert!(status.success(), "{lines}");
    assert!(rogue.sent() >= 1, "the rogue never got a request: {lines}");
    assert_eq!(read_json(&local_json), read_json(&remote_json), "{lines}");
    assert!(counter(&lines, "foreign replies") >= 1, "{lines}");

    // The rogue answers the next client's handshake too: refused, by name, nothing run.
    let out = pir2()
        .args(EVAL)
        .args(["5", "--checkpoint", ck_s, "--remote", &endpoint])
        .args(["--connect-timeout", "5"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("2 peers answered the handshake") && err.contains("refusing to pick one"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

/// An untrained ball-plate MLP checkpoint `dir/name` seeded `seed`, recording `policy`.
fn checkpoint_as(
    dir: &Path,
    name: &str,
    seed: u64,
    policy: Option<pir2_runtime::Policy>,
) -> PathBuf {
    let eps = demo::collect(3, 0, false).unwrap();
    let spec = demo::spec();
    let stats = compute_stats(&Episodes(&eps), &spec).unwrap();
    let cfg = Config {
        spec,
        model: ModelConfig::Mlp(MlpConfig {
            width: 32,
            depth: 2,
            ..MlpConfig::default()
        }),
    };
    let ck = dir.join(name);
    let mut m = CandleModel::new(cfg, stats, seed).unwrap();
    m.set_policy(policy);
    m.save(&ck).unwrap();
    ck
}

/// `pir2 eval --remote` refuses a server whose checkpoint differs from `--checkpoint` (other
/// weights, by their SHA-256) or was trained as another policy than `--policy`, by name, and
/// `pir2 serve policy --policy` refuses a checkpoint trained as another policy. Before: the
/// evaluation ran against whatever the server held.
#[test]
fn eval_remote_refuses_a_server_running_another_checkpoint() {
    use pir2_runtime::Policy;
    let s = Scratch::new("eval-remote-identity");
    let served = checkpoint_as(s.path(), "served", 3, Some(Policy::Rtc));
    let other = checkpoint_as(s.path(), "other", 4, Some(Policy::Rtc));
    // The served weights without identity.json (a checkpoint written before it existed).
    let old = s.path().join("old");
    std::fs::create_dir_all(&old).unwrap();
    for f in ["config.json", "stats.json", "model.safetensors"] {
        std::fs::copy(served.join(f), old.join(f)).unwrap();
    }

    let refused = pir2()
        .args([
            "serve",
            "policy",
            "--checkpoint",
            served.to_str().unwrap(),
            "--policy",
            "pir2",
        ])
        .args(["--listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{err}");
    assert!(
        err.contains("was trained as rtc; --policy pir2 would run it"),
        "{err}"
    );

    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _server = serve(&[
        "policy",
        "--checkpoint",
        served.to_str().unwrap(),
        "--listen",
        &endpoint,
    ]);
    let eval = |ck: &Path, policy: &str| {
        pir2()
            .args([
                "eval",
                "--policy",
                policy,
                "--d0",
                "1",
                "--episodes",
                "2",
                "--checkpoint",
            ])
            .arg(ck)
            .args(["--remote", &endpoint, "--connect-timeout", "20"])
            .output()
            .unwrap()
    };
    let out = eval(&other, "rtc");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains(&endpoint) && err.contains("runs other weights than checkpoint"),
        "{err}"
    );
    let out = eval(&old, "pir2");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("runs a checkpoint trained as rtc; --policy pir2 would run it"),
        "{err}"
    );
    let out = eval(&served, "rtc");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A client refuses to connect in plain TCP beyond this machine: one error naming the
/// endpoint and the fix, nothing dialled (before: `eval --remote tcp/OTHER-HOST:PORT` connected
/// and used whatever answered); `--insecure` lets it try, loudly.
#[test]
fn a_client_refuses_plain_tcp_beyond_loopback_without_insecure() {
    let s = Scratch::new("eval-insecure");
    let ck = checkpoint(s.path());
    // TEST-NET-1 (RFC 5737): routable syntax, never a real host.
    let endpoint = "tcp/192.0.2.1:7447";
    let eval = |extra: &[&str]| {
        let out = pir2()
            .args(EVAL)
            .args([
                "5",
                "--checkpoint",
                ck.to_str().unwrap(),
                "--remote",
                endpoint,
            ])
            .args(["--connect-timeout", "1"])
            .args(extra)
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let err = eval(&[]);
    assert!(
        err.contains("refusing to connect to `tcp/192.0.2.1:7447` without TLS"),
        "{err}"
    );
    assert!(!err.contains("no answer"), "it dialled: {err}");
    let err = eval(&["--insecure"]);
    assert!(err.contains("WARNING: --insecure"), "{err}");
    assert!(err.contains("no answer"), "{err}");
}

/// A TLS file that is not PEM is one error naming TLS and the file, on both sides, before
/// anything is dialled (before: the client waited, then reported "no answer").
#[test]
fn a_garbled_tls_file_is_named_on_both_sides() {
    let s = Scratch::new("tls-garbage");
    let garbage = s.path().join("garbage.pem");
    std::fs::write(&garbage, "not a certificate\n").unwrap();
    let g = garbage.to_str().unwrap();
    let tls = ["--tls-ca", g, "--tls-cert", g, "--tls-key", g];
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let out = pir2()
        .args([
            "serve",
            "policy",
            "--checkpoint",
            "unused",
            "--listen",
            &endpoint,
        ])
        .args(tls)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("TLS: the CA file") && err.contains(g) && err.contains("not a PEM"),
        "{err}"
    );
    let ck = checkpoint(s.path());
    let out = pir2()
        .args(EVAL)
        .args([
            "5",
            "--checkpoint",
            ck.to_str().unwrap(),
            "--remote",
            &endpoint,
        ])
        .args(["--connect-timeout", "1"])
        .args(tls)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("TLS: the CA file") && err.contains(g) && !err.contains("no answer"),
        "{err}"
    );
}

/// A CA certificate written to `dir/name.pem`, with its key (the certificates it signs).
fn test_ca(dir: &Path, name: &str) -> (rcgen::Certificate, rcgen::KeyPair, PathBuf) {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, KeyPair};
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    p.distinguished_name.push(DnType::CommonName, name);
    let key = KeyPair::generate().unwrap();
    let cert = p.self_signed(&key).unwrap();
    let pem = dir.join(format!("{name}.pem"));
    std::fs::write(&pem, cert.pem()).unwrap();
    (cert, key, pem)
}

/// `--tls-ca trust --tls-cert --tls-key` of a certificate for 127.0.0.1 signed by `issuer`.
fn tls_args(
    dir: &Path,
    name: &str,
    issuer: &(rcgen::Certificate, rcgen::KeyPair, PathBuf),
    trust: &Path,
) -> Vec<String> {
    let mut p = rcgen::CertificateParams::new(vec!["127.0.0.1".to_string()]).unwrap();
    p.distinguished_name.push(rcgen::DnType::CommonName, name);
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = p.signed_by(&key, &issuer.0, &issuer.1).unwrap();
    let (c, k) = (
        dir.join(format!("{name}.crt")),
        dir.join(format!("{name}.key")),
    );
    std::fs::write(&c, cert.pem()).unwrap();
    std::fs::write(&k, key.serialize_pem()).unwrap();
    [
        "--tls-ca".into(),
        trust.display().to_string(),
        "--tls-cert".into(),
        c.display().to_string(),
        "--tls-key".into(),
        k.display().to_string(),
    ]
    .into()
}

/// Mutual TLS through the binary: `pir2 eval --remote tls/…` with certificates of the user's CA
/// gives the local eval's result; a robot that trusts another CA than the one that signed the
/// server's certificate ends in one error naming the TLS handshake and its cause (before: "no
/// answer" after the connect timeout).
#[test]
fn a_tls_handshake_the_servers_certificate_fails_is_named_as_such() {
    let s = Scratch::new("tls-handshake");
    let ck = checkpoint(s.path());
    let ck_s = ck.to_str().unwrap();
    let local_json = local_eval(s.path(), ck_s);
    let user_ca = test_ca(s.path(), "user-ca");
    let other_ca = test_ca(s.path(), "other-ca");
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let server_tls = tls_args(s.path(), "server", &user_ca, &user_ca.2);
    let mut server_args = vec!["policy", "--checkpoint", ck_s, "--listen", &endpoint];
    server_args.extend(server_tls.iter().map(String::as_str));
    let _server = serve(&server_args);

    let remote_json = s.path().join("remote.json");
    let good = tls_args(s.path(), "robot", &user_ca, &user_ca.2);
    let out = pir2()
        .args(EVAL)
        .args(["5", "--checkpoint", ck_s, "--remote", &endpoint, "--json"])
        .arg(&remote_json)
        .args(["--connect-timeout", "10"])
        .args(&good)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert_eq!(read_json(&local_json), read_json(&remote_json), "{err}");

    let wrong_ca = tls_args(s.path(), "robot-other-ca", &user_ca, &other_ca.2);
    let out = pir2()
        .args(EVAL)
        .args(["5", "--checkpoint", ck_s, "--remote", &endpoint])
        .args(["--connect-timeout", "3"])
        .args(&wrong_ca)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("TLS: the TLS handshake with `tls/127.0.0.1:")
            && err.contains("not signed by"),
        "{err}"
    );
    assert!(
        !err.contains("no answer") && !err.contains("panicked"),
        "{err}"
    );
}

/// `pir2 gr00t run --remote-slow` fed by `pir2 gr00t serve slow`, while a rogue Zenoh client
/// of the server re-publishes each of its frames under another sender with every value set
/// to 1e6 (well-formed, fresh, wrong): the run uses the server's frames and counts the
/// rogue's (before: any publisher on the key fed the robot).
#[cfg(feature = "gr00t")]
#[test]
fn gr00t_run_with_the_backbone_behind_pir2_serve_slow() {
    use pir2_backends::gr00t::testing::{python_from_env, write_tiny_checkpoint};
    use pir2_runtime::testing::rogue::{Attach, Rogue};

    let s = Scratch::new("gr00t-remote-slow");
    let ck = s.path().join("ck");
    write_tiny_checkpoint(&ck, "", &python_from_env().unwrap()).unwrap();
    let ck_s = ck.to_str().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _server = gr00t_serve(&[
        "slow",
        "--checkpoint",
        ck_s,
        "--task",
        "catch_book",
        "--listen",
        &endpoint,
    ]);
    let rogue =
        Rogue::features_republisher(&Attach::ClientOf(endpoint.clone()), "pir2/slow", 1e6).unwrap();
    let json = s.path().join("run.json");
    let out = pir2()
        .args(["gr00t", "run", "gr00t-xarm-xhand", "--checkpoint", ck_s])
        .args(["--task", "catch the book", "--emulate", "--ticks", "50"])
        .args(["--remote-slow", &endpoint, "--slow-timeout", "20", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    eprintln!("{text}");
    assert!(out.status.success(), "{text}");
    let v = read_json(&json);
    assert_eq!(v["trace"]["ticks"], 50);
    assert!(v["trace"]["swaps"].as_u64().unwrap() >= 1);
    assert!(v["hand_commands"].as_u64().unwrap() >= 50);
    let r = &v["remote_slow"];
    assert!(r["frames"].as_u64().unwrap() >= 2, "{r}");
    assert!(r["clock_syncs"].as_u64().unwrap() >= 1, "{r}");
    assert!(rogue.sent() >= 1, "the rogue saw no frame of the server");
    assert!(r["foreign_replies"].as_u64().unwrap() >= 1, "{r}");
    let calls = v["trace"]["calls"].as_array().unwrap();
    assert!(!calls.is_empty());
    assert!(calls.iter().all(|c| c["d_vis"].as_u64().unwrap() <= 5));
}

/// `pir2 gr00t run … --remote-policy`: the GR00T action head behind `pir2 gr00t serve policy`.
#[cfg(feature = "gr00t")]
mod remote_head {
    use super::*;
    use pir2_backends::gr00t::testing::{python_from_env, write_tiny_checkpoint};

    fn gr00t_checkpoint(s: &Scratch) -> PathBuf {
        let ck = s.path().join("ck");
        write_tiny_checkpoint(&ck, "", &python_from_env().unwrap()).unwrap();
        ck
    }

    fn head_server(ck: &str, endpoint: &str, extra: &[&str]) -> Server {
        let mut a = vec![
            "policy",
            "--checkpoint",
            ck,
            "--task",
            "catch_book",
            "--listen",
            endpoint,
        ];
        a.extend_from_slice(extra);
        gr00t_serve(&a)
    }

    fn head_server_piped(ck: &str, endpoint: &str) -> Server {
        Server(
            pir2()
                .args(["gr00t", "serve", "policy", "--checkpoint", ck])
                .args(["--task", "catch_book"])
                .args(["--listen", endpoint])
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .expect("spawn pir2 gr00t serve"),
        )
    }

    /// `pir2 gr00t run` with the head at `endpoint`, stderr piped; returns once it is connected.
    // The child is returned to the caller, which waits for it.
    #[allow(clippy::zombie_processes)]
    fn start_run(
        ck: &str,
        endpoint: &str,
        json: &Path,
        extra: &[&str],
    ) -> (Child, BufReader<std::process::ChildStderr>) {
        let mut run = pir2()
            .args(["gr00t", "run", "gr00t-xarm-xhand", "--checkpoint", ck])
            .args(["--task", "catch the book", "--emulate"])
            .args(["--remote-policy", endpoint, "--json"])
            .arg(json)
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut err = BufReader::new(run.stderr.take().unwrap());
        let mut lines = Vec::new();
        loop {
            let mut l = String::new();
            if err.read_line(&mut l).unwrap() == 0 {
                let _ = run.wait();
                panic!("run exited: {lines:?}");
            }
            let connected = l.contains("connected to the policy server");
            lines.push(l);
            if connected {
                return (run, err);
            }
        }
    }

    fn ds(v: &serde_json::Value) -> Vec<u64> {
        let mut d: Vec<u64> = v["trace"]["calls"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["d"].as_u64().unwrap())
            .collect();
        d.sort_unstable();
        d
    }

    /// A head server whose stderr is read until it has answered its first request (the
    /// run's warm start: the run is about to tick).
    fn wait_first_request(server: &mut Server) {
        let mut err = BufReader::new(server.0.stderr.take().unwrap());
        let mut lines = Vec::new();
        loop {
            let mut l = String::new();
            assert!(
                err.read_line(&mut l).unwrap() > 0,
                "server exited: {lines:?}"
            );
            let first = l.contains("answered the first request");
            lines.push(l);
            if first {
                // Keep draining so the server never blocks on a full pipe.
                std::thread::spawn(move || std::io::copy(&mut err, &mut std::io::sink()));
                return;
            }
        }
    }

    /// Calls per `d` (the last bin holds `d ≥ 7`).
    fn histogram(d: &[u64]) -> [u64; 8] {
        let mut h = [0u64; 8];
        for &d in d {
            h[(d as usize).min(7)] += 1;
        }
        h
    }

    #[test]
    fn gr00t_run_survives_a_policy_server_restart() {
        let s = Scratch::new("gr00t-remote-head");
        let ck = gr00t_checkpoint(&s);
        let ck_s = ck.to_str().unwrap();
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let mut server = head_server_piped(ck_s, &endpoint);
        let json = s.path().join("run.json");
        // 10 s at 25 Hz; up to 50 × 200 ms without a reply, and the control watchdog at its
        // 5 s ceiling, before a safety stop (the outage plus a restart on a loaded machine
        // takes more than the watchdog's default second).
        let (mut run, mut err) = start_run(
            ck_s,
            &endpoint,
            &json,
            &[
                "--ticks",
                "250",
                "--max-failed-calls",
                "50",
                "--stall-limit-ms",
                "5000",
            ],
        );
        wait_first_request(&mut server);
        // The outage must fall in the control phase (the warm-up is not in the trace).
        wait_under_control(&mut err);
        std::thread::sleep(Duration::from_millis(1000));
        drop(server);
        std::thread::sleep(Duration::from_millis(800));
        let still_running = run.try_wait().unwrap().is_none();
        let _server = head_server(ck_s, &endpoint, &[]);
        let mut rest = String::new();
        std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
        let status = run.wait().unwrap();
        eprintln!("{rest}");
        assert!(status.success(), "{rest}");
        assert!(
            still_running,
            "the run finished before the server was killed"
        );

        let v = read_json(&json);
        let t = &v["trace"];
        eprintln!(
            "restart run: ticks {} calls {} swaps {} overruns {} holds {} latency {} d {:?} remote {}",
            t["ticks"],
            t["calls"].as_array().map_or(0, |c| c.len()),
            t["swaps"],
            t["overruns"],
            t["holds"],
            t["call_latency"],
            histogram(&ds(&v)),
            v["remote_policy"]
        );
        assert_eq!(t["ticks"], 250);
        assert!(
            v["head"].as_str().unwrap().contains(&endpoint),
            "{}",
            v["head"]
        );
        assert!(v["hand_commands"].as_u64().unwrap() >= 250);
        let r = &v["remote_policy"];
        assert!(r["timeouts"].as_u64().unwrap() >= 1, "{r}");
        assert!(r["reconnects"].as_u64().unwrap() >= 1, "{r}");
        assert_eq!(r["failed_calls"], 0, "{r}");
        // Every runtime call went through the server (warm start and NFEs included).
        let calls = t["calls"].as_array().unwrap().len() as u64;
        assert!(
            calls >= 50 && r["calls"].as_u64().unwrap() >= calls,
            "{r} {calls}"
        );
        // The outage ran the overrun path: ticks without a fresh chunk.
        assert!(
            t["overruns"].as_u64().unwrap() + t["holds"].as_u64().unwrap() >= 1,
            "{t:?}"
        );
        // The outage call was measured whole (≥ 800 ms), so the window saw the network.
        let max_latency = t["calls"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["latency"].as_u64().unwrap())
            .max()
            .unwrap();
        assert!(
            max_latency >= 500_000_000,
            "max call latency {max_latency} ns"
        );
    }

    #[test]
    fn gr00t_run_d_follows_the_round_trip() {
        let s = Scratch::new("gr00t-remote-delay");
        let ck = gr00t_checkpoint(&s);
        let ck_s = ck.to_str().unwrap();
        let mut medians = Vec::new();
        for delay in ["0", "60"] {
            let endpoint = format!("tcp/127.0.0.1:{}", free_port());
            let _server = head_server(ck_s, &endpoint, &["--inject-delay-ms", delay]);
            let json = s.path().join(format!("run-{delay}.json"));
            let (mut run, mut err) = start_run(ck_s, &endpoint, &json, &["--ticks", "75"]);
            let mut rest = String::new();
            std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
            assert!(run.wait().unwrap().success(), "{rest}");
            let v = read_json(&json);
            let d = ds(&v);
            eprintln!(
                "delay {delay} ms: latency {} d {:?} overruns {} remote last rtt {}",
                v["trace"]["call_latency"],
                histogram(&d),
                v["trace"]["overruns"],
                v["remote_policy"]["last_rtt_ns"]
            );
            assert!(!d.is_empty());
            medians.push(d[d.len() / 2]);
        }
        // 40 ms ticks: a prompt server gives d = 1; a 60 ms round trip needs d = 2.
        assert_eq!(medians[0], 1, "{medians:?}");
        assert!(medians[1] >= 2, "{medians:?}");
    }

    /// A run against a fresh policy server on `name`'s scratch, with `extra` flags; the
    /// server is killed `after` the control phase began. Returns the scratch, the endpoint,
    /// the `--json` path, the run's exit status, its stderr from then on, and how long after
    /// the kill it ended.
    fn lose_the_server_mid_run(
        name: &str,
        extra: &[&str],
        after: Duration,
    ) -> (
        Scratch,
        String,
        PathBuf,
        std::process::ExitStatus,
        String,
        Duration,
    ) {
        let s = Scratch::new(name);
        let ck = gr00t_checkpoint(&s);
        let ck_s = ck.to_str().unwrap();
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let mut server = head_server_piped(ck_s, &endpoint);
        let json = s.path().join("run.json");
        let (mut run, mut err) = start_run(ck_s, &endpoint, &json, extra);
        wait_first_request(&mut server);
        wait_under_control(&mut err);
        std::thread::sleep(after);
        drop(server);
        let t0 = Instant::now();
        let mut rest = String::new();
        std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
        let status = run.wait().unwrap();
        let took = t0.elapsed();
        eprintln!("{rest}");
        (s, endpoint, json, status, rest, took)
    }

    #[test]
    fn gr00t_run_stops_the_robot_when_the_policy_server_is_gone() {
        let (_s, endpoint, json, status, rest, took) = lose_the_server_mid_run(
            "gr00t-remote-gone",
            &[
                "--seconds",
                "60",
                "--max-failed-calls",
                "5",
                "--policy-timeout-ms",
                "100",
            ],
            Duration::from_millis(500),
        );
        assert!(!status.success());
        // 5 × 100 ms without a reply, then a safety stop that names the server.
        assert!(took < Duration::from_secs(15), "{took:?}");
        assert!(
            rest.contains("safety stop") && rest.contains(&endpoint),
            "{rest}"
        );
        assert!(rest.contains("failed_calls: 1"), "{rest}");
        assert!(!rest.contains("panicked"), "{rest}");
        // A failed run records its failure (not a summary) in --json.
        let report = std::fs::read_to_string(&json).expect("the failure report must be written");
        let v: serde_json::Value = serde_json::from_str(&report).unwrap();
        let error = v["error"].as_str().expect("a failure report has an error");
        assert!(error.contains("safety stop"), "{report}");
        // It keeps the trace of the ticks before the stop (before: the trace was lost).
        assert!(
            v["trace"]["ticks"].as_u64().unwrap_or(0) > 0
                && !v["trace"]["calls"].as_array().unwrap().is_empty(),
            "a failure keeps its trace: {report}"
        );
    }

    /// A second SIGINT ends the process at once (exit 130) after the emergency stop, and
    /// `--json` still gets the failure report with the limits in force (before: no file).
    #[test]
    fn a_second_signal_still_writes_the_failure_report() {
        let s = Scratch::new("gr00t-remote-second-signal");
        let ck = gr00t_checkpoint(&s);
        let ck_s = ck.to_str().unwrap();
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let mut server = head_server_piped(ck_s, &endpoint);
        let json = s.path().join("run.json");
        let (mut run, mut err) = start_run(ck_s, &endpoint, &json, &["--seconds", "60"]);
        wait_first_request(&mut server);
        wait_under_control(&mut err);
        for _ in 0..2 {
            // SAFETY: plain kill(2) on our own child.
            assert_eq!(unsafe { libc::kill(run.id() as i32, libc::SIGINT) }, 0);
            std::thread::sleep(Duration::from_millis(5));
        }
        let status = run.wait().unwrap();
        let mut rest = String::new();
        std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
        // The first signal may have ended the run cleanly before the second one arrived.
        let report = std::fs::read_to_string(&json).expect("--json must be written");
        let v: serde_json::Value = serde_json::from_str(&report).unwrap();
        eprintln!("exit {status:?}: {report}");
        if status.code() == Some(130) {
            let error = v["error"].as_str().expect("a failure report");
            assert!(error.contains("second SIGINT/SIGTERM"), "{report}");
            assert!(v["limits"]["control_hz"].as_f64().is_some(), "{report}");
        } else {
            assert!(status.success(), "{status:?}: {rest}");
            assert!(v["trace"]["ticks"].as_u64().is_some(), "{report}");
        }
    }

    /// The control watchdog through the binary: with the remote layer told to wait 50 ×
    /// 200 ms, a policy server that dies still stops the robot after `--stall-limit-ms` of
    /// ticks without a clean action, naming the watchdog (the robot is stopped before the
    /// workers are joined, and the call still retrying is abandoned).
    #[test]
    fn gr00t_run_stops_on_the_control_watchdog_when_the_policy_stalls() {
        let (_s, _endpoint, json, status, rest, took) = lose_the_server_mid_run(
            "gr00t-remote-stall",
            &[
                "--seconds",
                "60",
                "--max-failed-calls",
                "50",
                "--stall-limit-ms",
                "400",
            ],
            Duration::from_millis(300),
        );
        assert!(!status.success());
        // The watchdog's stop comes first (400 ms = 10 ticks at 25 Hz; the first error is
        // the one reported). The action worker's call in flight is then abandoned at its next
        // attempt instead of retrying its 50 × 200 ms = 10 s, so the process exits soon after.
        assert!(
            rest.contains("safety stop: control watchdog") && rest.contains("(bound 10;"),
            "{rest}"
        );
        assert!(took < Duration::from_secs(8), "{took:?}");
        let v = read_json(&json);
        assert_eq!(v["limits"]["stall_limit_ms"], 400.0, "{v}");
    }

    #[test]
    fn gr00t_run_without_a_policy_server_fails_before_the_robot_connects() {
        let s = Scratch::new("gr00t-remote-none");
        let ck = gr00t_checkpoint(&s);
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        // Real-robot arguments pointing nowhere: the error must be the server's, i.e. no
        // robot connection was attempted.
        let out = pir2()
            .args(["gr00t", "run", "gr00t-xarm-xhand", "--checkpoint"])
            .arg(&ck)
            .args(["--task", "catch_book", "--xarm", "10.255.255.1"])
            .args(["--xhand", "/nonexistent/ttyUSB0", "--synthetic-camera"])
            .args(["--remote-policy", &endpoint, "--connect-timeout", "1"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(
            err.contains(&endpoint)
                && err.contains("pir2 gr00t serve policy")
                && !err.contains("xArm"),
            "{err}"
        );
    }
}
/// `pir2 gr00t run --emulate --remote-slow` with its stderr piped; returns once a stderr line
/// contains `marker` (e.g. the run has received its first slow features).
#[cfg(feature = "gr00t")]
#[allow(clippy::zombie_processes)]
fn start_slow_run(
    ck: &str,
    endpoint: &str,
    extra: &[&str],
    marker: &str,
) -> (Child, BufReader<std::process::ChildStderr>) {
    let mut run = pir2()
        .args(["gr00t", "run", "gr00t-xarm-xhand", "--checkpoint", ck])
        .args(["--task", "catch the book", "--emulate"])
        .args(["--remote-slow", endpoint])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(run.stderr.take().unwrap());
    let mut lines = Vec::new();
    loop {
        let mut l = String::new();
        if err.read_line(&mut l).unwrap() == 0 {
            let _ = run.wait();
            panic!("run exited: {lines:?}");
        }
        let seen = l.contains(marker);
        lines.push(l);
        if seen {
            return (run, err);
        }
    }
}

/// Killing `pir2 gr00t serve slow` mid-run ends `pir2 gr00t run` in a safety stop within the
/// stale-slow grace (before: `pir2 gr00t run` never enabled the stale-slow check and the slow
/// source re-served the last features forever, so the run went on to its end on a frozen
/// image).
#[cfg(feature = "gr00t")]
#[test]
fn gr00t_run_stops_within_the_grace_when_the_slow_server_dies() {
    use pir2_backends::gr00t::testing::{python_from_env, write_tiny_checkpoint};

    let s = Scratch::new("gr00t-slow-dies");
    let ck = s.path().join("ck");
    write_tiny_checkpoint(&ck, "", &python_from_env().unwrap()).unwrap();
    let ck_s = ck.to_str().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let server = gr00t_serve(&[
        "slow",
        "--checkpoint",
        ck_s,
        "--task",
        "catch_book",
        "--listen",
        &endpoint,
    ]);
    // 2000 ticks at 25 Hz: 80 s if nothing stops it.
    let (mut run, mut err) = start_slow_run(
        ck_s,
        &endpoint,
        &[
            "--ticks",
            "2000",
            "--slow-timeout",
            "20",
            "--slow-grace-ms",
            "200",
        ],
        "connected to the slow server",
    );
    // Into the control phase, then long enough for it to run, short enough that a loaded
    // machine does not trip another safety stop (state watchdog, slow grace) before the kill.
    wait_under_control(&mut err);
    std::thread::sleep(Duration::from_millis(500));
    let alive = run.try_wait().unwrap().is_none();
    drop(server);
    let t_kill = Instant::now();
    let status = run.wait().unwrap();
    let took = t_kill.elapsed();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    eprintln!("run ended {took:?} after the kill: {rest}");
    assert!(alive, "the run ended before the server was killed: {rest}");
    assert!(!status.success(), "{rest}");
    assert!(
        rest.contains("safety stop") && rest.contains("slow features are"),
        "{rest}"
    );
    // (d_vis_max + ½)·T + grace = 220 + 200 ms, plus the process's own wind-down.
    assert!(
        took < Duration::from_secs(5),
        "stopped {took:?} after the kill"
    );
}

/// SIGTERM while `pir2 gr00t run` waits for its first backbone features (warm-up) stops the
/// emulated arm (`SET_STATE 4`) and ends the run at once (before: SIGTERM killed the process
/// without stopping the arm, and SIGINT was ignored until the warm-up ended).
#[cfg(feature = "gr00t")]
#[test]
fn sigterm_during_warm_up_stops_the_emulated_arm() {
    use pir2_backends::gr00t::testing::{python_from_env, write_tiny_checkpoint};

    let s = Scratch::new("gr00t-sigterm");
    let ck = s.path().join("ck");
    write_tiny_checkpoint(&ck, "", &python_from_env().unwrap()).unwrap();
    let ck_s = ck.to_str().unwrap();
    // Nobody serves this endpoint: the run waits for its first features (60 s).
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let (mut run, mut err) = start_slow_run(
        ck_s,
        &endpoint,
        &["--slow-timeout", "60"],
        "waiting for the first features",
    );
    std::thread::sleep(Duration::from_millis(500));
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(run.id() as i32, libc::SIGTERM) }, 0);
    let t0 = Instant::now();
    let status = run.wait().unwrap();
    let took = t0.elapsed();
    let mut out = String::new();
    std::io::Read::read_to_string(run.stdout.as_mut().unwrap(), &mut out).unwrap();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    assert!(status.success(), "{out}{rest}");
    assert!(
        took < Duration::from_secs(5),
        "exited {took:?} after SIGTERM"
    );
    assert!(
        out.contains("stop requested during the warm-up"),
        "{out}{rest}"
    );
    assert!(
        out.contains("arm state at the end (emulator): 4"),
        "{out}{rest}"
    );
}

/// `pir2 serve` refuses to listen beyond this machine without TLS (one error naming the
/// endpoint and the way out), accepts it with `--insecure` and says so loudly, and a
/// half-given TLS triple is refused (before: it listened on any address in plain TCP).
#[test]
fn serve_refuses_a_public_address_without_tls() {
    let out = pir2()
        .args(["serve", "slow", "--stub", "4", "--listen", "tcp/0.0.0.0:0"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("refusing to listen on `tcp/0.0.0.0:0` without TLS"),
        "{err}"
    );

    let out = pir2()
        .args(["serve", "slow", "--stub", "4", "--listen", "tcp/0.0.0.0:0"])
        .args(["--tls-ca", "ca.pem"])
        .output()
        .unwrap();
    assert!(!out.status.success());

    let port = free_port();
    let mut s = pir2()
        .args(["serve", "slow", "--stub", "4", "--insecure"])
        .args(["--listen", &format!("tcp/0.0.0.0:{port}")])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(s.stderr.take().unwrap());
    let mut first = String::new();
    err.read_line(&mut first).unwrap();
    let _ = s.kill();
    let _ = s.wait();
    assert!(
        first.contains("WARNING: --insecure") && first.contains("WITHOUT TLS"),
        "{first}"
    );
}
