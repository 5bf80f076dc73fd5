//! Round trips, typed errors and garbage inputs of every message family.

use super::*;
use crate::model::{ModelInput, SlowInput};
use proptest::prelude::*;

fn hdr(kind: Kind) -> Header {
    Header {
        kind,
        sender: 7,
        seq: 42,
        t_a: 1_000,
        t_b: 2_000,
    }
}

#[test]
fn version_mismatch_is_a_typed_error() {
    let bytes = Writer::with_version(hdr(Kind::Ping), 0, 0, WIRE_VERSION + 1).finish();
    assert_eq!(
        decode(&bytes).unwrap_err(),
        WireError::Version {
            got: WIRE_VERSION + 1,
            expected: WIRE_VERSION
        }
    );
    let msg = decode_pong(&bytes).unwrap_err().to_string();
    assert!(
        msg.contains(&format!("v{}", WIRE_VERSION + 1))
            && msg.contains(&format!("v{WIRE_VERSION}")),
        "{msg}"
    );
}

#[test]
fn bad_magic_and_kind_and_trailing_bytes() {
    let mut bytes = encode_ping(1, 2, 3);
    assert_eq!(decode(&bytes).unwrap().header.kind, Kind::Ping);
    bytes.push(0);
    assert!(matches!(decode(&bytes), Err(WireError::Malformed(_))));
    bytes.pop();
    bytes[6] = 99;
    assert_eq!(decode(&bytes).unwrap_err(), WireError::UnknownKind(99));
    bytes[0] = b'X';
    assert!(matches!(decode(&bytes), Err(WireError::BadMagic(_))));
    assert!(matches!(
        decode(&bytes[..10]),
        Err(WireError::Truncated { .. })
    ));
}

#[test]
fn huge_declared_tensor_is_rejected_without_allocating() {
    let mut bytes = Writer::new(hdr(Kind::Features), 0, 0).finish();
    bytes[7] = 1; // one tensor, declared [u32::MAX, u32::MAX] f32 with no data
    bytes.extend_from_slice(&[1, 2, 0, 0]);
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        decode(&bytes),
        Err(WireError::Truncated { .. }) | Err(WireError::Malformed(_))
    ));
}

#[test]
fn wrong_kind_is_reported() {
    let bytes = encode_ping(1, 2, 3);
    assert_eq!(
        decode_features(&bytes).unwrap_err(),
        WireError::UnexpectedKind {
            expected: Kind::Features,
            got: Kind::Ping
        }
    );
    let e = encode_error(1, 2, "model exploded");
    assert_eq!(
        decode_reply(&e).unwrap(),
        Reply::Error("model exploded".into())
    );
}

#[test]
fn request_len_matches_encoding() {
    let x = vec![0.5; 2 * 3 * 4];
    let tau = vec![0.0; 2 * 3];
    let obs = vec![1.0; 2 * 2 * 5];
    let slow = vec![2.0; 2 * 3 * 6];
    let dv = [1, 2];
    let input = ModelInput {
        batch: 2,
        horizon: 3,
        action_dim: 4,
        x: &x,
        tau: &tau,
        obs_fast: &obs,
        n_obs: 2,
        fast_dim: 5,
        slow: SlowInput::Tokens {
            data: &slow,
            tokens: 3,
            dim: 6,
        },
        d_vis: &dv,
    };
    let bytes = encode_request(1, 2, 3, &input);
    assert_eq!(bytes.len(), request_len(&input));
}

fn slow_strategy(b: usize) -> impl Strategy<Value = SlowOwned> {
    prop_oneof![
        Just(SlowOwned::None),
        (1usize..6).prop_flat_map(move |dim| {
            prop::collection::vec(-1e6f32..1e6, b * dim)
                .prop_map(move |data| SlowOwned::Vector { data, dim })
        }),
        (1usize..4, 1usize..5).prop_flat_map(move |(tokens, dim)| {
            prop::collection::vec(-1e6f32..1e6, b * tokens * dim)
                .prop_map(move |data| SlowOwned::Tokens { data, tokens, dim })
        }),
    ]
}

fn request_strategy() -> impl Strategy<Value = Request> {
    (
        1usize..3,
        1usize..6,
        1usize..5,
        1usize..3,
        1usize..5,
        any::<[u64; 3]>(),
    )
        .prop_flat_map(|(b, h, a, n_obs, f, ids)| {
            (
                prop::collection::vec(any::<f32>(), b * h * a),
                prop::collection::vec(0f32..=1.0, b * h),
                prop::collection::vec(any::<f32>(), b * n_obs * f),
                prop::collection::vec(0u32..10, b),
                slow_strategy(b),
            )
                .prop_map(move |(x, tau, obs_fast, d_vis, slow)| Request {
                    header: Header {
                        kind: Kind::PolicyRequest,
                        sender: ids[0],
                        seq: ids[1],
                        t_a: ids[2],
                        t_b: 0,
                    },
                    batch: b,
                    horizon: h,
                    action_dim: a,
                    n_obs,
                    fast_dim: f,
                    x,
                    tau,
                    obs_fast,
                    d_vis,
                    slow,
                })
        })
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Proptest settings: 256 cases per property in CI, `PIR2_FUZZ_CASES` more
/// (`scripts/check-extra.sh`); shrunk failures kept in `proptest-regressions/wire.txt`. The
/// integration tests of other crates take the same rule from `pir2_tests::fuzz_cases`; this
/// unit test cannot, since pir2-tests depends on this crate.
fn fuzz_cases() -> ProptestConfig {
    let cases = std::env::var("PIR2_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(256);
    ProptestConfig {
        cases,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::Direct("proptest-regressions/wire.txt"),
        )),
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(fuzz_cases())]

    #[test]
    fn request_round_trips_bit_exactly(req in request_strategy()) {
        let bytes = encode_request(req.header.sender, req.header.seq, req.header.t_a, &req.input());
        let back = decode_request(&bytes).unwrap();
        prop_assert_eq!(back.header, req.header);
        prop_assert_eq!((back.batch, back.horizon, back.action_dim, back.n_obs, back.fast_dim),
            (req.batch, req.horizon, req.action_dim, req.n_obs, req.fast_dim));
        prop_assert_eq!(bits(&back.x), bits(&req.x)); // NaN payloads survive too
        prop_assert_eq!(bits(&back.tau), bits(&req.tau));
        prop_assert_eq!(bits(&back.obs_fast), bits(&req.obs_fast));
        prop_assert_eq!(&back.d_vis, &req.d_vis);
        prop_assert_eq!(&back.slow, &req.slow);
        back.input().validate().unwrap();
    }

    #[test]
    fn features_round_trip(tokens in 0usize..5, dim in 0usize..7, seed in any::<u64>(), t in any::<[u64; 2]>()) {
        let data: Vec<f32> = (0..tokens * dim).map(|i| (i as f32) * 0.5 - seed as f32).collect();
        let bytes = encode_features(seed, seed ^ 1, t[0], t[1], tokens, dim, &data);
        let m = decode_features(&bytes).unwrap();
        prop_assert_eq!(m, FeaturesMsg { sender: seed, seq: seed ^ 1, t_capture: t[0], t_sent: t[1], tokens, dim, data });
    }

    #[test]
    fn reply_and_pong_round_trip(seq in any::<u64>(), t in any::<[u64; 3]>(), v in prop::collection::vec(any::<f32>(), 6)) {
        let req = Header { kind: Kind::PolicyRequest, sender: 1, seq, t_a: t[0], t_b: 0 };
        match decode_reply(&encode_reply(9, &req, t[1], [1, 2, 3], &v)).unwrap() {
            Reply::Velocity { header, shape, v: back } => {
                prop_assert_eq!(header.seq, seq);
                prop_assert_eq!(header.t_a, t[0]);
                prop_assert_eq!(header.t_b, t[1]);
                prop_assert_eq!(shape, vec![1, 2, 3]);
                prop_assert_eq!(bits(&back), bits(&v));
            }
            Reply::Error(e) => prop_assert!(false, "{}", e),
        }
        let ping = decode(&encode_ping(3, seq, t[0])).unwrap().header;
        let pong = decode_pong(&encode_pong(4, &ping, t[2])).unwrap();
        prop_assert_eq!((pong.seq, pong.t_a, pong.t_b, pong.sender), (seq, t[0], t[2], 4));
    }

    #[test]
    fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = decode(&bytes);
        let _ = decode_request(&bytes);
        let _ = decode_features(&bytes);
        let _ = decode_reply(&bytes);
        let _ = decode_pong(&bytes);
    }

    #[test]
    fn corrupted_valid_messages_never_panic(req in request_strategy(), flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8), cut in any::<prop::sample::Index>()) {
        let mut bytes = encode_request(1, 2, 3, &req.input());
        // Keep magic and version intact so the corruption reaches the tensor parser.
        for (i, b) in &flips {
            let k = 6 + i.index(bytes.len() - 6);
            bytes[k] = *b;
        }
        let _ = decode_request(&bytes);
        let n = cut.index(bytes.len() + 1);
        let _ = decode_request(&bytes[..n]);
        let _ = decode_reply(&bytes[..n]);
    }
}

/// A pong carries a policy server's identity when it has one; a pong without one (an older
/// server) still decodes, and both decode as a plain pong.
#[test]
fn a_pong_carries_the_server_identity_or_none() {
    let ping = decode(&encode_ping(1, 7, 42)).unwrap().header;
    let with = encode_pong_with_identity(2, &ping, 99, Some(r#"{"policy":"rtc"}"#));
    let (h, id) = decode_pong_identity(&with).unwrap();
    assert_eq!((h.seq, h.t_a, h.t_b), (7, 42, 99));
    assert_eq!(id.as_deref(), Some(r#"{"policy":"rtc"}"#));
    assert_eq!(decode_pong(&with).unwrap(), h);
    let without = encode_pong(2, &ping, 99);
    assert_eq!(decode_pong_identity(&without).unwrap(), (h, None));
}
