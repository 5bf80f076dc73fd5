//! The xArm wire format as firmware sends it: every report frame size the official SDK
//! (`xarm-python-sdk` 1.18.4) accepts, written out byte by byte at the SDK's offsets (not
//! with this crate's encoder), the SDK's report validation, the version strings real
//! controllers send, and frames split or concatenated at arbitrary points.

use pir2_robots::xarm::proto::{
    self, FirmwareVersion, FrameBuf, Reply, Report, ReportBuf, ReportKind,
};
use pir2_robots::Error;
use proptest::prelude::*;

fn put_f32(b: &mut [u8], at: usize, v: f32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

/// A frame of `len` bytes with size header `header` and the common part: state 2, mode 1,
/// cmd_num 7, j1 = 0.25, j6 = -0.5, x = 250 mm, tau2 = 3.5.
fn common(len: usize, header: u32) -> Vec<u8> {
    let mut b = vec![0u8; len];
    b[..4].copy_from_slice(&header.to_be_bytes());
    b[4] = 0x12;
    b[5..7].copy_from_slice(&7u16.to_be_bytes());
    put_f32(&mut b, 7, 0.25);
    put_f32(&mut b, 7 + 5 * 4, -0.5);
    put_f32(&mut b, 35, 250.0);
    put_f32(&mut b, 59 + 4, 3.5);
    b
}

fn check_common(r: &Report) {
    assert_eq!((r.state, r.mode, r.cmd_num), (2, 1, 7));
    assert_eq!(r.angles[0], 0.25);
    assert_eq!(r.angles[5], -0.5);
    assert_eq!(r.pose[0], 250.0);
    assert_eq!(r.torques[1], 3.5);
}

/// Normal-layout fields at 87..145: brake/enable bits, error 31, warning 11, TCP offset z =
/// 50, payload 1.5 kg, sensitivities 3 and 2, gravity (0, 0, -1) when `len >= 145`.
fn normal(len: usize, header: u32) -> Vec<u8> {
    let mut b = common(len, header);
    b[87] = 0x3f;
    b[88] = 0x3f;
    b[89] = 31;
    b[90] = 11;
    put_f32(&mut b, 91 + 8, 50.0);
    put_f32(&mut b, 115, 1.5);
    b[131] = 3;
    b[132] = 2;
    if len >= 145 {
        put_f32(&mut b, 133 + 8, -1.0);
    }
    b
}

#[test]
fn real_report_87_bytes_legacy() {
    let b = common(87, 87);
    let r = Report::parse(&b, ReportKind::Real).unwrap();
    check_common(&r);
    assert_eq!(r.ft, None);
    assert_eq!(r.size, 87);
}

#[test]
fn real_report_135_bytes_carries_ft_forces_at_87_and_111() {
    let mut b = common(135, 135);
    put_f32(&mut b, 87 + 8, 12.5); // external Fz
    put_f32(&mut b, 111, -2.0); // raw Fx
    let r = Report::parse(&b, ReportKind::Real).unwrap();
    check_common(&r);
    let (ext, raw) = r.ft.unwrap();
    assert_eq!((ext[2], raw[0]), (12.5, -2.0));
    // Our encoder writes the same bytes.
    assert_eq!(r.encode(ReportKind::Real, 135).unwrap(), b);
}

#[test]
fn normal_report_133_bytes_legacy_and_145_current() {
    let r = Report::parse(&normal(133, 133), ReportKind::Normal).unwrap();
    check_common(&r);
    assert_eq!(
        (r.brake_bits, r.enable_bits, r.error, r.warning),
        (0x3f, 0x3f, 31, 11)
    );
    assert_eq!((r.collision_sens, r.teach_sens), (3, 2));
    assert_eq!(r.tcp_offset[2], 50.0);
    assert_eq!(r.tcp_load[0], 1.5);
    assert_eq!(r.gravity, None);
    let b = normal(145, 145);
    let r = Report::parse(&b, ReportKind::Normal).unwrap();
    assert_eq!(r.gravity, Some([0.0, 0.0, -1.0]));
    assert_eq!(r.encode(ReportKind::Normal, 145).unwrap(), b);
}

/// A rich frame at the SDK's current offsets: type 6, axis 6 @145, version text @151,
/// limits @181, temperatures @245, counter @284, simulation flag @314, F/T @433.
fn rich(len: usize, header: u32) -> Vec<u8> {
    let mut b = normal(len, header);
    b[145] = 6;
    b[146] = 6;
    b[151..157].copy_from_slice(b"v2.6.0");
    put_f32(&mut b, 181 + 4 * 9, 4.0); // joint max speed
    if len >= 252 {
        b[245] = 31;
        b[251] = (-5i8) as u8;
    }
    if len >= 288 {
        b[284..288].copy_from_slice(&1234u32.to_be_bytes());
    }
    if len >= 417 {
        b[314] = 1;
        b[315] = 1;
    }
    if len >= 481 {
        put_f32(&mut b, 433, 7.0);
    }
    b
}

#[test]
fn rich_report_587_bytes_per_the_sdk_layout() {
    let b = rich(587, 587);
    let r = Report::parse(&b, ReportKind::Rich).unwrap();
    check_common(&r);
    assert_eq!(r.error, 31);
    let info = r.rich.unwrap();
    assert_eq!((info.arm_type, info.axis), (6, 6));
    assert_eq!(info.version_str(), "v2.6.0");
    assert_eq!(info.limits[9], 4.0);
    assert_eq!(info.temperatures, Some([31, 0, 0, 0, 0, 0, -5]));
    assert_eq!(info.counter, Some(1234));
    assert_eq!(info.simulation, Some(true));
    assert_eq!(r.ft.unwrap().0[0], 7.0);
    assert_eq!(r.encode(ReportKind::Rich, 587).unwrap(), b);
}

#[test]
fn rich_report_245_bytes_under_a_233_size_header_is_taken_whole() {
    // Firmware that added the gravity direction without updating the size header.
    let f = rich(245, 233);
    let mut rb = ReportBuf::new(ReportKind::Rich);
    rb.push(&f);
    rb.push(&f);
    let a = rb.next_report().unwrap().unwrap();
    let b = rb.next_report().unwrap().unwrap();
    assert_eq!(a, b);
    assert_eq!(a.size, 245);
    assert_eq!(a.rich.unwrap().axis, 6);
    assert_eq!(rb.size(), Some(245));
}

#[test]
fn rich_report_of_really_233_bytes_is_taken_at_233() {
    let f = normal(233, 233);
    let mut rb = ReportBuf::new(ReportKind::Rich);
    rb.push(&f);
    // 233 or 245 is decided only once the next header's place is in view.
    assert!(rb.next_report().unwrap().is_none());
    rb.push(&f);
    rb.push(&f);
    for _ in 0..3 {
        let r = rb.next_report().unwrap().unwrap();
        assert_eq!(r.size, 233);
        assert_eq!(r.rich, None, "legacy offsets past 133 are not parsed");
    }
    assert_eq!(rb.size(), Some(233));
}

#[test]
fn normal_and_rich_reports_are_validated_like_the_sdk_does() {
    for kind in [ReportKind::Normal, ReportKind::Rich] {
        let len = kind.current_len();
        let ok = if kind == ReportKind::Rich {
            rich(len, len as u32)
        } else {
            normal(len, len as u32)
        };
        assert!(Report::parse(&ok, kind).is_ok());
        for (at, v, what) in [
            (131, 6u8, "collision sensitivity"),
            (132, 9, "teach sensitivity"),
            (4, 0xc2, "mode"),
            (4, 0x1a, "state"),
        ] {
            let mut b = ok.clone();
            b[at] = v;
            let err = Report::parse(&b, kind).unwrap_err();
            assert!(
                matches!(err, Error::XArmFrame { ref reason } if reason.contains(what)),
                "{kind:?} {what}: {err}"
            );
        }
        // A size header that disagrees with the frame.
        let mut b = ok.clone();
        b[3] ^= 1;
        assert!(matches!(
            Report::parse(&b, kind),
            Err(Error::XArmReportSize { .. })
        ));
    }
    // The real stream is not validated beyond its size (the SDK does not either).
    let mut b = common(135, 135);
    b[4] = 0xcf;
    assert!(Report::parse(&b, ReportKind::Real).is_ok());
}

#[test]
fn reports_shorter_than_the_legacy_size_of_their_stream_are_refused() {
    for (kind, short) in [
        (ReportKind::Real, 86usize),
        (ReportKind::Normal, 132),
        (ReportKind::Rich, 145),
    ] {
        let b = normal(short.max(133), short as u32);
        let mut rb = ReportBuf::new(kind);
        rb.push(&b[..short.min(b.len())]);
        assert!(
            matches!(rb.next_report(), Err(Error::XArmReportSize { .. })),
            "{kind:?} {short}"
        );
    }
}

#[test]
fn version_strings_of_real_controllers() {
    let v = FirmwareVersion::parse("6,6,XI1203,XX0000,v1.6.9\0\0\0").unwrap();
    assert_eq!((v.axis, v.arm_type), (Some(6), Some(6)));
    assert_eq!(v.robot_sn.as_deref(), Some("XI1203"));
    assert_eq!(v.control_box_sn.as_deref(), Some("XX0000"));
    assert_eq!(v.number, (1, 6, 9));
    assert_eq!(v.protocol_id(), 2, "1.6.9 is older than 1.8.6");
    assert_eq!(v.set_mode_params(1), vec![1]);
    assert!(!v.has_joint_states());

    let v = FirmwareVersion::parse("7,7,XS1304,AC1303,v2.5.5").unwrap();
    assert_eq!(v.axis, Some(7));
    assert_eq!(v.protocol_id(), proto::PROTO_PRIVATE_V3);
    assert_eq!(v.set_mode_params(1), vec![1, 0]);
    assert!(v.has_joint_states());

    let v = FirmwareVersion::parse("6,9,LI1002,DL1000,v1.11.4").unwrap();
    assert_eq!(
        (v.axis, v.arm_type, v.number),
        (Some(6), Some(9), (1, 11, 4))
    );

    // No commas: the SDK finds the number but keeps its default axis (7); we leave it unknown.
    let v = FirmwareVersion::parse("xArm-emu 2.0.0").unwrap();
    assert_eq!((v.axis, v.number), (None, (2, 0, 0)));

    // Thresholds.
    let at = |s: &str| FirmwareVersion::parse(&format!("6,6,XI1304,AC1303,v{s}")).unwrap();
    assert_eq!(at("1.8.5").protocol_id(), 2);
    assert_eq!(at("1.8.6").protocol_id(), 3);
    assert_eq!(at("1.9.109").set_mode_params(1), vec![1]);
    assert!(!at("1.9.109").has_joint_states());
    assert!(at("1.9.110").has_joint_states());
    assert_eq!(at("1.10.0").set_mode_params(1), vec![1, 0]);

    // V0 date strings are refused with the string named.
    let err = FirmwareVersion::parse("xArm-Controller-2018-12-20").unwrap_err();
    assert!(
        matches!(err, Error::XArmFrame { ref reason } if reason.contains("2018-12-20")),
        "{err}"
    );
}

#[test]
fn sdk_heartbeat_frame_is_a_protocol_1_frame() {
    let mut fb = FrameBuf::new();
    fb.push(&proto::HEARTBEAT_FRAME);
    let f = fb.next_frame().unwrap().unwrap();
    let c = proto::Command::decode(&f).unwrap();
    assert_eq!((c.tid, c.proto), (0, proto::PROTO_HEARTBEAT));
}

fn replies(n: usize) -> Vec<Reply> {
    (0..n)
        .map(|i| Reply {
            tid: i as u16 + 1,
            proto: 3,
            register: [42u8, 13, 29, 0xff][i % 4],
            status: (i % 3) as u8 * 0x10,
            data: vec![i as u8; i * 7 % 90],
        })
        .collect()
}

proptest! {
    #![proptest_config(pir2_tests::fuzz_cases(128, "proptest-regressions/xarm_wire.txt"))]

    /// Replies concatenated into one stream and cut at arbitrary points come out whole and
    /// in order.
    #[test]
    fn reply_stream_split_anywhere(n in 1usize..8, cuts in proptest::collection::vec(any::<prop::sample::Index>(), 0..12)) {
        let rs = replies(n);
        let stream: Vec<u8> = rs.iter().flat_map(|r| r.encode().unwrap()).collect();
        let mut points: Vec<usize> = cuts.iter().map(|c| c.index(stream.len() + 1)).collect();
        points.push(0);
        points.push(stream.len());
        points.sort_unstable();
        let mut fb = FrameBuf::new();
        let mut got = Vec::new();
        for w in points.windows(2) {
            fb.push(&stream[w[0]..w[1]]);
            while let Some(f) = fb.next_frame().unwrap() {
                got.push(Reply::decode(&f).unwrap());
            }
        }
        prop_assert_eq!(got, rs);
        prop_assert_eq!(fb.pending(), 0);
    }

    /// Report frames of every size the SDK accepts, three in a row, cut at arbitrary points.
    #[test]
    fn report_stream_split_anywhere(which in 0usize..7, cuts in proptest::collection::vec(any::<prop::sample::Index>(), 0..12)) {
        let (kind, frame) = match which {
            0 => (ReportKind::Real, common(87, 87)),
            1 => (ReportKind::Real, common(135, 135)),
            2 => (ReportKind::Normal, normal(133, 133)),
            3 => (ReportKind::Normal, normal(145, 145)),
            4 => (ReportKind::Rich, normal(233, 233)),
            5 => (ReportKind::Rich, rich(245, 233)),
            _ => (ReportKind::Rich, rich(587, 587)),
        };
        let stream: Vec<u8> = (0..3).flat_map(|_| frame.clone()).collect();
        let mut points: Vec<usize> = cuts.iter().map(|c| c.index(stream.len() + 1)).collect();
        points.push(0);
        points.push(stream.len());
        points.sort_unstable();
        let mut rb = ReportBuf::new(kind);
        let mut got = Vec::new();
        for w in points.windows(2) {
            rb.push(&stream[w[0]..w[1]]);
            while let Some(r) = rb.next_report().unwrap() {
                got.push(r);
            }
        }
        prop_assert_eq!(got.len(), 3);
        for r in &got {
            prop_assert_eq!(r.state, 2);
            prop_assert_eq!(r.angles[0], 0.25);
            prop_assert_eq!(r.size as usize, frame.len());
        }
    }
}
