//! Tests of the embodiment configuration, the `[policy]` table and the normaliser.
use super::*;

#[test]
fn xarm6_xhand_matches_the_paper() {
    let c = EmbodimentConfig::xarm6_xhand();
    c.validate().unwrap();
    assert_eq!(c.state_dim(), 45);
    assert_eq!(c.action_dim(), 18);
    assert_eq!((c.horizon, c.d_max, c.d_vis_max), (50, 5, 5));
    assert_eq!(c.period_ns(), 40_000_000);
    assert_eq!(c.prompt_for("catch_book"), "catch the book");
    assert_eq!(c.prompt_for("catch the book"), "catch the book");
    assert_eq!(c.tasks.len(), 4);
    let back: EmbodimentConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
    assert_eq!(back, c);
}

/// `[safety]` in embodiment.toml: grace and per-group limits are read, flattened over
/// the action vector, and bad values are one error naming the field (before: hand limits
/// and tracking bounds were placeholders in code, not configurable).
#[test]
fn safety_section_is_parsed_flattened_and_checked() {
    let text = "slow_grace_ms = 150.0\n\n[limits.hand_joints]\n\
                lower = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.2]\n\
                upper = [1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.5, 1.0]\n\
                max_velocity = 3.0\ntracking_error = 0.4\n";
    let mut c = EmbodimentConfig::xarm6_xhand();
    c.safety = toml::from_str(text).unwrap();
    // The whole file round-trips with the table in it.
    let c: EmbodimentConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
    c.validate().unwrap();
    assert_eq!(c.slow_grace_ns(), 150_000_000);
    let l = c.action_limits();
    assert_eq!(l.lower.len(), 18);
    assert_eq!(
        (l.lower[0], l.lower[6], l.lower[17]),
        (None, Some(0.0), Some(-0.2))
    );
    assert_eq!(
        (l.upper[17], l.max_velocity[6], l.max_velocity[5]),
        (Some(1.0), Some(3.0), None)
    );
    assert_eq!((l.tracking_error[10], l.max_accel[10]), (Some(0.4), None));
    // Defaults when the table is absent.
    let d = EmbodimentConfig::xarm6_xhand();
    assert_eq!(d.slow_grace_ns(), 200_000_000);
    assert!(d.action_limits().lower.iter().all(Option::is_none));
    // Errors name the field.
    let bad = |edit: &dyn Fn(&mut EmbodimentConfig), want: &str| {
        let mut c = EmbodimentConfig::xarm6_xhand();
        edit(&mut c);
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains(want), "{e}");
    };
    bad(&|c| c.safety.slow_grace_ms = 0.0, "slow_grace_ms");
    // A checkpoint cannot widen the envelope past the ceilings (before: 1e9 ms and 1e9 Hz ran).
    bad(
        &|c| c.safety.slow_grace_ms = 1e9,
        "safety.slow_grace_ms must be in (0, 1000]",
    );
    bad(&|c| c.control_hz = 1e9, "control_hz must be in (0, 250]");
    let mut edge = EmbodimentConfig::xarm6_xhand();
    (edge.safety.slow_grace_ms, edge.control_hz) = (MAX_SLOW_GRACE_MS, MAX_CONTROL_HZ);
    edge.validate().unwrap();
    bad(
        &|c| {
            c.safety
                .limits
                .insert("wrist".into(), GroupLimits::default());
        },
        "safety.limits.wrist",
    );
    bad(
        &|c| {
            c.safety.limits.insert(
                "hand_joints".into(),
                GroupLimits {
                    lower: Some(vec![0.0; 5]),
                    ..Default::default()
                },
            );
        },
        "hand_joints.lower has 5 values",
    );
    bad(
        &|c| {
            c.safety.limits.insert(
                "arm_joints".into(),
                GroupLimits {
                    max_velocity: Some(-1.0),
                    ..Default::default()
                },
            );
        },
        "arm_joints.max_velocity",
    );
    assert!(toml::from_str::<SafetySection>("grace = 1").is_err());
}

/// The action groups must be the robot's by name and order, not only by total width.
#[test]
fn action_groups_are_checked_by_name_and_order() {
    let robot = [("arm_joints", 6), ("hand_joints", 12)];
    let c = EmbodimentConfig::xarm6_xhand();
    c.check_action_groups(&robot).unwrap();
    let mut swapped = c.clone();
    swapped.action.reverse();
    assert_eq!(swapped.action_dim(), 18);
    let e = swapped.check_action_groups(&robot).unwrap_err().to_string();
    assert!(e.contains("do not match"), "{e}");
    let mut renamed = c;
    renamed.action[1].name = "gripper".into();
    assert!(renamed.check_action_groups(&robot).is_err());
}

fn stats_json(drop: Option<&str>) -> String {
    let c = EmbodimentConfig::xarm6_xhand();
    let mut emb = serde_json::Map::new();
    for (m, groups) in [("state", &c.state), ("action", &c.action)] {
        let mut gm = serde_json::Map::new();
        for g in groups.iter() {
            let mut s = serde_json::Map::new();
            for (k, v) in [("min", -2.0), ("max", 4.0), ("mean", 1.0), ("std", 2.0)] {
                if drop == Some(&format!("{m}.{}.{k}", g.name)) {
                    continue;
                }
                s.insert(k.into(), serde_json::json!(vec![v; g.dim]));
            }
            gm.insert(g.name.clone(), s.into());
        }
        emb.insert(m.into(), gm.into());
    }
    serde_json::json!({ "new_embodiment": emb }).to_string()
}

#[test]
fn min_max_maps_to_unit_interval_and_back() {
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-stats-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("statistics.json");
    std::fs::write(&p, stats_json(None)).unwrap();
    let c = EmbodimentConfig::xarm6_xhand();
    let n = Normalizer::load(&p, &c).unwrap();
    let mut out = vec![0.0; 45];
    n.normalize_state(&[-2.0; 45], &mut out);
    assert!(out.iter().all(|x| (*x + 1.0).abs() < 1e-6), "{out:?}");
    n.normalize_state(&[1.0; 45], &mut out);
    assert!(out.iter().all(|x| x.abs() < 1e-6));
    n.normalize_state(&[100.0; 45], &mut out);
    assert!(out.iter().all(|x| *x == 1.0), "clipped");
    let mut a = vec![1.0; 18];
    n.denormalize_action(&mut a);
    assert!(a.iter().all(|x| (*x - 4.0).abs() < 1e-6));

    std::fs::write(&p, stats_json(Some("state.hand_torques.max"))).unwrap();
    let e = Normalizer::load(&p, &c).unwrap_err().to_string();
    assert!(
        e.contains("new_embodiment.state.hand_torques.max") && e.contains("missing"),
        "{e}"
    );

    // Statistics that would invert or blow up the actions are refused by key (before: min >
    // max flipped every action of the group and 1e30 ran).
    let edited = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut v: serde_json::Value = serde_json::from_str(&stats_json(None)).unwrap();
        edit(&mut v["new_embodiment"]);
        std::fs::write(&p, v.to_string()).unwrap();
        Normalizer::load(&p, &c).unwrap_err().to_string()
    };
    let e = edited(&|v| v["action"]["hand_joints"]["min"][3] = serde_json::json!(5.0));
    assert!(
        e.contains("new_embodiment.action.hand_joints.max") && e.contains("inverted"),
        "{e}"
    );
    let e = edited(&|v| v["action"]["arm_joints"]["max"][0] = serde_json::json!(1e30));
    assert!(
        e.contains("new_embodiment.action.arm_joints.max") && e.contains("[0] = 1e30"),
        "{e}"
    );
    let mut ms = c.clone();
    ms.state[0].norm = Norm::MeanStd;
    let mut v: serde_json::Value = serde_json::from_str(&stats_json(None)).unwrap();
    v["new_embodiment"]["state"][&ms.state[0].name]["std"][0] = serde_json::json!(-1.0);
    std::fs::write(&p, v.to_string()).unwrap();
    let e = Normalizer::load(&p, &ms).unwrap_err().to_string();
    assert!(e.contains(".std") && e.contains("negative"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn every_row_of_the_robot_table_resolves_from_the_policy_table() {
    use pir2_runtime::{Mode, Policy};
    use pir2_schedule::{Alignment, FrontMode};
    // No [policy] table: a πR² head (n = 2) in πR² async, as before the table existed.
    let c = EmbodimentConfig::xarm6_xhand();
    assert_eq!(
        c.policy.mode(&ModeOverrides::default()).unwrap(),
        Mode::PiR2Async {
            nfe: Some(2),
            alignment: Alignment::Fresh,
            front: FrontMode::Visible
        }
    );
    let section = |text: &str| -> PolicySection { toml::from_str(text).unwrap() };
    let flow = section("trained = \"flow\"\nmode = \"sync_flow\"\nflow_steps = 4\nh = 10");
    let over = |mode: DeployKind| ModeOverrides {
        mode: Some(mode),
        ..Default::default()
    };
    assert_eq!(
        flow.mode(&ModeOverrides::default()).unwrap(),
        Mode::SyncFlow { steps: 4, h: 10 }
    );
    assert_eq!(
        flow.mode(&ModeOverrides {
            ensemble: Some(Some(0.1)),
            ..over(DeployKind::NaiveAsync)
        })
        .unwrap(),
        Mode::NaiveAsync {
            steps: 4,
            ensemble: Some(0.1)
        }
    );
    assert_eq!(
        flow.mode(&over(DeployKind::InferenceRtc)).unwrap(),
        Mode::InferenceRtc {
            steps: 4,
            overlap: None,
            ramp_rate: 5.0
        }
    );
    let irtc = section(
        "trained = \"flow\"\nmode = \"inference_rtc\"\nrtc_overlap = 8\nrtc_ramp_rate = 6.0",
    );
    assert_eq!(
        irtc.mode(&ModeOverrides::default()).unwrap(),
        Mode::InferenceRtc {
            steps: 4,
            overlap: Some(8),
            ramp_rate: 6.0
        }
    );
    for (text, want) in [
        ("rtc_overlap = 0", "rtc_overlap must be >= 1"),
        ("rtc_ramp_rate = -1.0", "rtc_ramp_rate = -1"),
        ("rtc_ramp_rate = nan", "rtc_ramp_rate = NaN"),
    ] {
        let bad = section(&format!(
            "trained = \"flow\"\nmode = \"inference_rtc\"\n{text}"
        ));
        let e = bad.mode(&ModeOverrides::default()).unwrap_err().to_string();
        assert!(e.contains(want), "{text}: {e}");
    }
    let rtc = section("trained = \"rtc\"\nmode = \"rtc\"\nflow_steps = 4");
    assert_eq!(
        rtc.mode(&ModeOverrides::default()).unwrap(),
        Mode::TrainTimeRtc { steps: 4 }
    );
    let full = section("trained = \"pi_r2_full\"");
    assert_eq!(
        full.mode(&over(DeployKind::PiR2Sync)).unwrap(),
        Mode::PiR2Sync {
            nfe: None,
            alignment: Alignment::Paper,
            front: FrontMode::Visible
        }
    );
    let hidden = section("trained = \"pi_r2_hidden\"\nnfe = 3");
    assert_eq!(
        hidden.mode(&ModeOverrides::default()).unwrap(),
        Mode::PiR2Async {
            nfe: Some(3),
            alignment: Alignment::Fresh,
            front: FrontMode::Hidden
        }
    );
    // Mismatches name both sides.
    let e = c
        .policy
        .mode(&over(DeployKind::Rtc))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("mode rtc") && e.contains("trained = \"pi_r2\""),
        "{e}"
    );
    let e = flow
        .mode(&over(DeployKind::PiR2Async))
        .unwrap_err()
        .to_string();
    assert!(e.contains("pir2_async") && e.contains("\"flow\""), "{e}");
    let e = c
        .policy
        .mode(&ModeOverrides {
            nfe: Some(4),
            ..Default::default()
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("--nfe 4") && e.contains("nfe = 2"), "{e}");
    let e = flow
        .mode(&ModeOverrides {
            h: Some(0),
            ..Default::default()
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("h must be >= 1"), "{e}");
    let e = flow
        .mode(&ModeOverrides {
            ensemble: Some(Some(1.5)),
            ..over(DeployKind::NaiveAsync)
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("ensemble = 1.5"), "{e}");
    // Unknown modes and keys are refused by the TOML reader.
    assert!(toml::from_str::<PolicySection>("mode = \"fast\"").is_err());
    assert!(toml::from_str::<PolicySection>("steps = 4").is_err());
    assert_eq!(policy_name(Policy::PiR2Hidden), "pi_r2_hidden");
    for k in DeployKind::ALL {
        assert_eq!(DeployKind::parse(k.name()), Some(k));
    }
}

/// GR00T's edge cases (its `normalize_values_minmax`, `normalize_values_meanstd`,
/// `unnormalize_values_minmax`, `apply_sin_cos_encoding`, with `clip_outliers`): a min/max
/// dimension with `max = min` normalises to 0 and decodes to `min`; a zero-std dimension
/// passes through; a min/max action is clipped to `[-1, 1]` before it is decoded; a sin/cos
/// group is `[sin…, cos…]` with no statistics. Expected values computed by hand from those
/// definitions.
#[test]
fn normalisation_follows_gr00ts_edge_cases_and_sin_cos_encoding() {
    let mut c = EmbodimentConfig::xarm6_xhand();
    let group = |name: &str, dim, norm| Group {
        norm,
        ..Group::new(name, dim)
    };
    c.state = vec![
        group("pos", 3, Norm::MinMax),
        group("vel", 2, Norm::MeanStd),
        group("angle", 2, Norm::SinCos),
    ];
    c.action = vec![
        group("target", 2, Norm::MinMax),
        group("grip", 1, Norm::MeanStd),
    ];
    assert_eq!((c.state_dim(), c.encoded_state_dim()), (7, 9));
    // No statistics for the sin/cos group: none are needed.
    let stats = serde_json::json!({ "new_embodiment": {
        "state": {
            "pos": { "min": [0.0, 5.0, -1.0], "max": [2.0, 5.0, 1.0] },
            "vel": { "mean": [1.0, 2.0], "std": [2.0, 0.0] },
        },
        "action": {
            "target": { "min": [-1.0, 3.0], "max": [1.0, 3.0] },
            "grip": { "mean": [0.5], "std": [0.0] },
        },
    }});
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-edge-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("statistics.json");
    std::fs::write(&p, stats.to_string()).unwrap();
    let n = Normalizer::load(&p, &c).unwrap();
    assert_eq!((n.state_dim(), n.encoded_state_dim()), (7, 9));

    let mut out = vec![f32::NAN; 9];
    n.normalize_state(&[1.0, 7.0, 3.0, 5.0, 9.0, 0.5, 2.0], &mut out);
    let want = [
        0.0, // (1 − 0)/2·2 − 1
        0.0, // max = min
        1.0, // 2·(3 + 1)/2 − 1 = 3, clipped
        2.0, // (5 − 1)/2
        9.0, // std 0: unchanged
        0.5f32.sin(),
        2.0f32.sin(),
        0.5f32.cos(),
        2.0f32.cos(),
    ];
    for (k, (o, w)) in out.iter().zip(want).enumerate() {
        assert!((o - w).abs() < 1e-6, "state[{k}] = {o}, GR00T gives {w}");
    }

    // Decoding: (clip(x) + 1)/2·(max − min) + min; std 0 passes the model's value through.
    let mut a = [2.0, 0.3, 0.25];
    n.denormalize_action(&mut a);
    assert_eq!(a, [1.0, 3.0, 0.25]);
    // The runtime's output map decodes the same way.
    let mut u = [0.0; 3];
    n.action_output_map().apply(&[2.0, 0.3, 0.25], &mut u);
    assert_eq!(u, a);

    // Encoding training targets: (x − mid)/half-range clipped, max = min → 0, std 0 → x;
    // decoding inverts it inside the clip range.
    let mut t = [0.5, 7.0, 0.25];
    n.normalize_action(&mut t);
    assert_eq!(t, [0.5, 0.0, 0.25]);
    let mut far = [5.0, 3.0, -4.0];
    n.normalize_action(&mut far);
    assert_eq!(far, [1.0, 0.0, -4.0]);
    let mut back = [0.5, 0.0, 0.25];
    n.denormalize_action(&mut back);
    assert_eq!(back, [0.5, 3.0, 0.25]);

    // sin/cos is a state encoding only.
    c.action[1].norm = Norm::SinCos;
    let e = c.validate().unwrap_err().to_string();
    assert!(
        e.contains("action group `grip`") && e.contains("sin_cos"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A relative joint group (GR00T's `use_relative_action`): its statistics are
/// `relative_action.<group>`, per chunk slot (`[H, D]`) or `[D]`; decoding a slot clips,
/// denormalises with that slot's statistics and adds the newest raw state of the group's
/// `state_key`, as GR00T's `unapply` does. Expected values worked by hand. A wrong shape is
/// one error naming the key and both shapes.
#[test]
fn relative_action_statistics_are_read_per_slot_and_decode_like_gr00t() {
    let mut c = EmbodimentConfig::xarm6_xhand();
    c.horizon = 3;
    c.d_max = 1;
    c.state = vec![Group::new("hand", 1), Group::new("arm", 2)];
    c.action = vec![
        Group {
            relative: true,
            ..Group::new("arm", 2)
        },
        Group::new("hand", 1),
    ];
    c.validate().unwrap();
    assert_eq!(c.action_reference(), [Some(1), Some(2), None]);
    // `relative` and `state_key` survive the TOML round trip; absent, they are not written.
    let text = c.to_toml().unwrap();
    assert_eq!(text.matches("relative = true").count(), 1, "{text}");
    assert!(
        !text.contains("state_key") && !text.contains("format"),
        "{text}"
    );
    assert_eq!(toml::from_str::<EmbodimentConfig>(&text).unwrap(), c);

    let per_slot = serde_json::json!([[-0.1, -0.2], [-0.2, -0.4], [-0.3, -0.6]]);
    let stats = |rel_min: serde_json::Value, rel_max: serde_json::Value| {
        serde_json::json!({ "new_embodiment": {
            "state": {
                "arm": { "min": [-3.0, -3.0], "max": [3.0, 3.0] },
                "hand": { "min": [0.0], "max": [1.0] },
            },
            "action": {
                "hand": { "min": [0.0], "max": [1.0] },
                // The absolute statistics of a relative group are not used.
                "arm": { "min": [-9.0, -9.0], "max": [9.0, 9.0] },
            },
            "relative_action": { "arm": { "min": rel_min, "max": rel_max } },
        }})
        .to_string()
    };
    let neg = |v: &serde_json::Value| -> serde_json::Value {
        serde_json::from_str(&v.to_string().replace('-', "")).unwrap()
    };
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-rel-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("statistics.json");
    std::fs::write(&p, stats(per_slot.clone(), neg(&per_slot))).unwrap();
    let n = Normalizer::load(&p, &c).unwrap();
    assert!(n.per_slot());

    // Raw state [hand, arm₀, arm₁] = [0.3, 0.5, −1.0]; the model's action at slot 1.
    let state = [0.3, 0.5, -1.0];
    let x = [0.5, 2.0, 0.5];
    // arm₀: (0.5 + 1)/2·(0.2 − (−0.2)) − 0.2 = 0.1, + 0.5 → 0.6
    // arm₁: clip(2) = 1 → (1 + 1)/2·0.8 − 0.4 = 0.4, − 1.0 → −0.6
    // hand (absolute): (0.5 + 1)/2·1 + 0 = 0.75
    let want = [0.6, -0.6, 0.75];
    let mut a = x;
    n.decode_action(1, &state, &mut a);
    assert!(
        a.iter().zip(want).all(|(x, w)| (x - w).abs() < 1e-6),
        "{a:?} vs {want:?}"
    );
    // The runtime's output map decodes the same chunk slot the same way.
    let map = n.action_output_map();
    assert_eq!(map.reference, [Some(1), Some(2), None]);
    assert_eq!((map.scale.len(), map.clip.len()), (9, 3));
    let (mut r, mut u) = ([0.0; 3], [0.0; 3]);
    map.fill_reference(&state, &mut r);
    map.decode(&x, 1, &r, &mut u);
    assert!(
        u.iter().zip(want).all(|(x, w)| (x - w).abs() < 1e-6),
        "{u:?} vs {want:?}"
    );
    // Slot 2 uses its own statistics: arm₀ = 0.75·0.6 − 0.3 + 0.5.
    map.decode(&x, 2, &r, &mut u);
    assert!((u[0] - 0.65).abs() < 1e-6, "{u:?}");

    // Training targets (GR00T's apply_action): the absolute actions [0.6, −0.7, 0.75] at
    // slot 1 against the same state: arm₀ 0.6 − 0.5 = 0.1 → (0.1 − (−0.2))/0.4·2 − 1 = 0.5;
    // arm₁ −0.7 + 1.0 = 0.3 → (0.3 + 0.4)/0.8·2 − 1 = 0.75; hand 0.75 → 0.5.
    let mut z = [0.6, -0.7, 0.75];
    n.encode_action(1, &state, &mut z);
    let want_z = [0.5, 0.75, 0.5];
    assert!(
        z.iter().zip(want_z).all(|(x, w)| (x - w).abs() < 1e-6),
        "{z:?} vs {want_z:?}"
    );
    // ... which the runtime decodes back to the actions (the round trip inside the range);
    // a target outside the slot's range is clipped (arm₁ at slot 0: −0.7 + 1.0 = 0.3 > 0.2).
    map.decode(&z, 1, &r, &mut u);
    assert!(
        u.iter()
            .zip([0.6, -0.7, 0.75])
            .all(|(x, w)| (x - w).abs() < 1e-6),
        "{u:?}"
    );
    let mut z = [0.6, -0.7, 0.75];
    n.encode_action(0, &state, &mut z);
    assert_eq!(z[1], 1.0, "{z:?}");

    // `[D]` statistics: the same range at every slot.
    std::fs::write(
        &p,
        stats(
            serde_json::json!([-0.2, -0.4]),
            serde_json::json!([0.2, 0.4]),
        ),
    )
    .unwrap();
    let n = Normalizer::load(&p, &c).unwrap();
    assert!(!n.per_slot());
    let mut a = x;
    n.decode_action(2, &state, &mut a);
    assert!(
        (a[0] - 0.6).abs() < 1e-6 && (a[1] + 0.6).abs() < 1e-6,
        "{a:?}"
    );

    // Wrong shapes: one error naming the key and both shapes.
    let short = serde_json::json!([[-0.1, -0.2], [-0.2, -0.4]]);
    std::fs::write(&p, stats(short.clone(), neg(&short))).unwrap();
    let e = Normalizer::load(&p, &c).unwrap_err().to_string();
    assert!(
        e.contains("new_embodiment.relative_action.arm.min")
            && e.contains("has shape [2, 2]")
            && e.contains("expected [3, 2] (per chunk slot) or [2]"),
        "{e}"
    );
    std::fs::write(
        &p,
        stats(
            serde_json::json!([-0.2, -0.4, 0.0]),
            serde_json::json!([0.2, 0.4]),
        ),
    )
    .unwrap();
    let e = Normalizer::load(&p, &c).unwrap_err().to_string();
    assert!(
        e.contains("relative_action.arm.min") && e.contains("[3]"),
        "{e}"
    );
    // A per-slot table is only for relative groups.
    let mut abs = c.clone();
    abs.action[0].relative = false;
    let mut v: serde_json::Value =
        serde_json::from_str(&stats(per_slot.clone(), neg(&per_slot))).unwrap();
    v["new_embodiment"]["action"]["arm"]["min"] = per_slot.clone();
    std::fs::write(&p, v.to_string()).unwrap();
    let e = Normalizer::load(&p, &abs).unwrap_err().to_string();
    assert!(
        e.contains("new_embodiment.action.arm.min") && e.contains("has shape [3, 2], expected [2]"),
        "{e}"
    );
    // A missing relative statistic is named.
    v["new_embodiment"]["relative_action"] = serde_json::json!({});
    std::fs::write(&p, v.to_string()).unwrap();
    let e = Normalizer::load(&p, &c).unwrap_err().to_string();
    assert!(
        e.contains("relative_action.arm.min") && e.contains("missing"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// The configuration errors of relative groups, each naming the group.
#[test]
fn relative_groups_are_checked_by_name() {
    let bad = |edit: &dyn Fn(&mut EmbodimentConfig), want: &[&str]| {
        let mut c = EmbodimentConfig::xarm6_xhand();
        edit(&mut c);
        let e = c.validate().unwrap_err().to_string();
        assert!(want.iter().all(|w| e.contains(w)), "{e}");
    };
    bad(
        &|c| {
            c.action[0].relative = true;
            c.action[0].state_key = Some("wrist".into());
        },
        &["`arm_joints`", "state group `wrist`", "does not exist"],
    );
    bad(
        &|c| {
            c.action[1].relative = true;
            c.action[1].state_key = Some("arm_joints".into());
        },
        &["`hand_joints` (dim 12)", "`arm_joints` of dim 6"],
    );
    bad(
        &|c| c.action[0].state_key = Some("arm_joints".into()),
        &[
            "`arm_joints`",
            "state_key is only used with relative = true",
        ],
    );
    bad(
        &|c| c.state[0].relative = true,
        &["state group `arm_joints`"],
    );
    // A relative pose against a state group of another width.
    bad(
        &|c| {
            c.action[0] = Group {
                relative: true,
                format: GroupFormat::XyzRot6d,
                ..Group::new("arm_joints", 9)
            };
        },
        &["`arm_joints` (dim 9)", "`arm_joints` of dim 6"],
    );
    bad(
        &|c| c.action[0].format = GroupFormat::XyzRot6d,
        &["`arm_joints`", "9 values", "dim 6"],
    );
    // An absolute pose group is only numbers to normalise: fine.
    let mut c = EmbodimentConfig::xarm6_xhand();
    c.action[0].format = GroupFormat::XyzRotvec;
    c.validate().unwrap();
    // A relative group with its state key spelled out.
    c.action[0].relative = true;
    c.action[0].format = GroupFormat::Default;
    c.action[0].state_key = Some("arm_joints".into());
    c.validate().unwrap();
    assert_eq!(
        c.action_reference()[..7],
        [Some(0), Some(1), Some(2), Some(3), Some(4), Some(5), None]
    );
}

/// A relative end-effector pose group (`xyz_rot6d`, relative to a state group read in the
/// same layout): GR00T's `T_ref⁻¹·T` as the training target, normalised per slot, and back
/// through both `Normalizer::decode_action` and the runtime's output map, with a hand-worked
/// case (see `pir2_runtime::pose`): reference at (1, 2, 0) turned 90° about z, target at
/// (0, 2, 1) turned 180° about z → relative (0, 1, 1) turned 90° about z.
#[test]
fn relative_end_effector_poses_encode_and_decode_like_gr00t() {
    let mut c = EmbodimentConfig::xarm6_xhand();
    c.horizon = 2;
    c.d_max = 1;
    c.state = vec![Group::new("grip", 1), Group::new("eef", 9)];
    c.action = vec![
        Group {
            relative: true,
            format: GroupFormat::XyzRot6d,
            ..Group::new("eef", 9)
        },
        Group::new("grip", 1),
    ];
    c.validate().unwrap();
    let poses = c.action_poses();
    assert_eq!(poses.len(), 1);
    assert_eq!(poses[0].first, 0);
    let text = c.to_toml().unwrap();
    assert!(text.contains("format = \"xyz_rot6d\""), "{text}");

    // Slot 0: range ±2 on every value (offset 0, scale 2); slot 1: ±4.
    let row = |v: f64| serde_json::json!(vec![v; 9]);
    let stats = serde_json::json!({ "new_embodiment": {
        "state": {
            "grip": { "min": [0.0], "max": [1.0] },
            "eef": { "min": vec![-3.0; 9], "max": vec![3.0; 9] },
        },
        "action": {
            "grip": { "min": [0.0], "max": [1.0] },
            "eef": { "min": vec![-9.0; 9], "max": vec![9.0; 9] },
        },
        "relative_action": { "eef": {
            "min": [row(-2.0), row(-4.0)],
            "max": [row(2.0), row(4.0)],
        } },
    }});
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-pose-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("statistics.json");
    std::fs::write(&p, stats.to_string()).unwrap();
    let n = Normalizer::load(&p, &c).unwrap();
    let state = [0.5, 1.0, 2.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
    let action = [0.0, 2.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.25];
    let rel = [0.0, 1.0, 1.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
    for slot in 0..2 {
        let scale = if slot == 0 { 2.0 } else { 4.0 };
        let mut z = action;
        n.encode_action(slot, &state, &mut z);
        for (x, r) in z.iter().zip(rel) {
            assert!((x - r / scale).abs() < 1e-6, "slot {slot}: {z:?}");
        }
        assert!((z[9] + 0.5).abs() < 1e-6, "{z:?}");
        let mut a = z;
        n.decode_action(slot, &state, &mut a);
        assert!(
            a.iter().zip(action).all(|(x, w)| (x - w).abs() < 1e-6),
            "slot {slot}: {a:?}"
        );
        let map = n.action_output_map();
        map.validate(2, 10).unwrap();
        let (mut r, mut u) = ([0.0; 10], [0.0; 10]);
        map.fill_reference(&state, &mut r);
        map.decode(&z, slot, &r, &mut u);
        assert!(
            u.iter().zip(action).all(|(x, w)| (x - w).abs() < 1e-6),
            "slot {slot}: {u:?}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
