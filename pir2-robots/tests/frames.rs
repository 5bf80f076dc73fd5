//! Round trips of every frame type against byte vectors written out by hand from the
//! protocol descriptions (module docs of `xarm::proto` and `xhand::proto`), and fuzzing of
//! every parser with proptest: arbitrary bytes never panic.
//!
//! The XHand CRCs below were computed independently of this crate with Python's
//! `binascii.crc_hqx(frame, 0)` (CRC-16/XMODEM).

use pir2_robots::xarm::proto::{
    self, next_tid, reg, Command, FrameBuf, Reply, Report, ReportBuf, ReportKind,
};
use pir2_robots::xhand::consts;
use pir2_robots::xhand::proto::{
    crc16_xmodem, decode_hand_command, encode_hand_command, FingerCommand, FingerState, Frame,
    FrameParser, HandState,
};
use pir2_robots::Error;
use proptest::prelude::*;

fn cmd(tid: u16, register: u8, params: &[u8]) -> Vec<u8> {
    Command {
        tid,
        proto: 2,
        register,
        params: params.to_vec(),
    }
    .encode()
    .unwrap()
}

// ---------------------------------------------------------------------------------------------
// xArm command frames
// ---------------------------------------------------------------------------------------------

#[test]
fn xarm_motion_enable_frame() {
    let f = cmd(1, reg::MOTION_EN, &[8, 1]);
    assert_eq!(f, [0x00, 0x01, 0x00, 0x02, 0x00, 0x03, 0x0b, 0x08, 0x01]);
    assert_eq!(Command::decode(&f).unwrap().params, vec![8, 1]);
}

#[test]
fn xarm_set_mode_set_state_get_state_clean_err_frames() {
    assert_eq!(
        cmd(2, reg::SET_MODE, &[1]),
        [0x00, 0x02, 0x00, 0x02, 0x00, 0x02, 0x13, 0x01]
    );
    assert_eq!(
        cmd(3, reg::SET_STATE, &[4]),
        [0x00, 0x03, 0x00, 0x02, 0x00, 0x02, 0x0c, 0x04]
    );
    assert_eq!(
        cmd(7, reg::GET_STATE, &[]),
        [0x00, 0x07, 0x00, 0x02, 0x00, 0x01, 0x0d]
    );
    assert_eq!(
        cmd(10, reg::CLEAN_ERR, &[]),
        [0x00, 0x0a, 0x00, 0x02, 0x00, 0x01, 0x10]
    );
    assert_eq!(
        cmd(11, reg::GET_ERROR, &[]),
        [0x00, 0x0b, 0x00, 0x02, 0x00, 0x01, 0x0f]
    );
    assert_eq!(
        cmd(12, reg::GET_VERSION, &[]),
        [0x00, 0x0c, 0x00, 0x02, 0x00, 0x01, 0x01]
    );
    assert_eq!(
        cmd(13, reg::GET_JOINT_POS, &[]),
        [0x00, 0x0d, 0x00, 0x02, 0x00, 0x01, 0x2a]
    );
    assert_eq!(
        cmd(14, reg::GET_JOINT_TAU, &[]),
        [0x00, 0x0e, 0x00, 0x02, 0x00, 0x01, 0x37]
    );
    // Transaction ids are big-endian.
    assert_eq!(&cmd(0x1234, reg::GET_STATE, &[])[..2], &[0x12, 0x34]);
}

#[test]
fn xarm_servoj_frame_is_ten_little_endian_fp32() {
    let f = cmd(
        1,
        reg::MOVE_SERVOJ,
        &proto::servoj_params(&[0.5, -2.0, 0.0, 0.0, 0.0, 1.0]),
    );
    let mut want = vec![0x00, 0x01, 0x00, 0x02, 0x00, 0x29, 0x1d];
    want.extend([0x00, 0x00, 0x00, 0x3f]); // 0.5
    want.extend([0x00, 0x00, 0x00, 0xc0]); // -2.0
    want.extend([0u8; 12]); // j3..j5
    want.extend([0x00, 0x00, 0x80, 0x3f]); // 1.0
    want.extend([0u8; 16]); // j7, speed, acc, mvtime
    assert_eq!(f.len(), 47);
    assert_eq!(f, want);
    let c = Command::decode(&f).unwrap();
    let mut v = [0f32; 10];
    proto::read_fp32s_le(&c.params, &mut v).unwrap();
    assert_eq!(v, [0.5, -2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
}

#[test]
fn xarm_replies_decode_from_hand_written_bytes() {
    // GET_STATE reply: tid 7, len 3, reg 13, status 0, state 2.
    let r = Reply::decode(&[0x00, 0x07, 0x00, 0x02, 0x00, 0x03, 0x0d, 0x00, 0x02]).unwrap();
    assert_eq!(
        (r.tid, r.proto, r.register, r.status, r.data.as_slice()),
        (7, 2, 13, 0, &[2u8][..])
    );
    // GET_ERROR reply with the error bit: error 31, warning 0.
    let r = Reply::decode(&[0x00, 0x09, 0x00, 0x02, 0x00, 0x04, 0x0f, 0x40, 0x1f, 0x00]).unwrap();
    assert_eq!(r.status, proto::status::ERROR);
    assert_eq!(r.data, vec![31, 0]);
    // GET_JOINT_POS reply: 7 fp32 LE, 1.0 and -1.0 first.
    let mut b = vec![0x00, 0x05, 0x00, 0x02, 0x00, 0x1e, 0x2a, 0x00];
    b.extend([0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x80, 0xbf]);
    b.extend([0u8; 20]);
    let r = Reply::decode(&b).unwrap();
    let mut q = [0f32; 7];
    proto::read_fp32s_le(&r.data, &mut q).unwrap();
    assert_eq!(q, [1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    assert_eq!(r.encode().unwrap(), b);
    // A servo-j acknowledgement: no data.
    let ack = Reply {
        tid: 300,
        proto: 2,
        register: 29,
        status: 0,
        data: vec![],
    };
    assert_eq!(
        ack.encode().unwrap(),
        [0x01, 0x2c, 0x00, 0x02, 0x00, 0x02, 0x1d, 0x00]
    );
    // GET_JOINT_TAU and GET_VERSION replies round-trip with their lengths.
    let tau = Reply {
        tid: 1,
        proto: 2,
        register: reg::GET_JOINT_TAU,
        status: 0,
        data: proto::fp32s_le(&[2.5; 7]),
    };
    assert_eq!(&tau.encode().unwrap()[4..6], &[0x00, 0x1e]);
    let ver = Reply {
        tid: 1,
        proto: 2,
        register: reg::GET_VERSION,
        status: 0,
        data: vec![b'v'; 40],
    };
    assert_eq!(&ver.encode().unwrap()[4..8], &[0x00, 0x2a, 0x01, 0x00]);
    assert_eq!(Reply::decode(&ver.encode().unwrap()).unwrap(), ver);
}

#[test]
fn xarm_frame_length_mismatch_is_named() {
    let err = Reply::decode(&[0x00, 0x07, 0x00, 0x02, 0x00, 0x05, 0x0d, 0x00, 0x02]).unwrap_err();
    assert!(
        matches!(err, Error::XArmFrame { ref reason } if reason.contains("length field 5")),
        "{err}"
    );
}

#[test]
fn xarm_transaction_ids_wrap_from_65535_to_1() {
    assert_eq!(next_tid(1), 2);
    assert_eq!(next_tid(65534), 65535);
    assert_eq!(next_tid(65535), 1);
}

#[test]
fn xarm_frame_buffer_splits_by_length_not_by_read() {
    let a = cmd(1, reg::MOTION_EN, &[8, 1]);
    let b = cmd(2, reg::GET_STATE, &[]);
    let mut stream = a.clone();
    stream.extend(&b);
    let mut fb = FrameBuf::new();
    // One byte at a time, then everything else at once.
    fb.push(&stream[..1]);
    assert_eq!(fb.next_frame().unwrap(), None);
    fb.push(&stream[1..8]);
    assert_eq!(fb.next_frame().unwrap(), None);
    fb.push(&stream[8..]);
    assert_eq!(fb.next_frame().unwrap(), Some(a));
    assert_eq!(fb.next_frame().unwrap(), Some(b));
    assert_eq!(fb.next_frame().unwrap(), None);
    assert_eq!(fb.pending(), 0);
}

#[test]
fn xarm_frame_buffer_rejects_an_impossible_length() {
    let mut fb = FrameBuf::new();
    fb.push(&[0x00, 0x01, 0x00, 0x02, 0xff, 0xff, 0x00]);
    assert!(matches!(fb.next_frame(), Err(Error::XArmFrame { .. })));
    assert_eq!(fb.pending(), 0);
}

// ---------------------------------------------------------------------------------------------
// xArm reports
// ---------------------------------------------------------------------------------------------

fn real_report_bytes() -> Vec<u8> {
    let mut b = vec![0u8; 87];
    b[..4].copy_from_slice(&[0x00, 0x00, 0x00, 0x57]); // size 87
    b[4] = 0x12; // mode 1 (high nibble), state 2 (low nibble)
    b[5..7].copy_from_slice(&[0x00, 0x05]); // cmd_num 5
    b[7..11].copy_from_slice(&[0x00, 0x00, 0x00, 0x3f]); // j1 = 0.5
    b[31..35].copy_from_slice(&[0x00, 0x00, 0x80, 0xbf]); // j7 = -1.0
    b[35..39].copy_from_slice(&[0x00, 0x00, 0x48, 0x43]); // x = 200.0
    b[59..63].copy_from_slice(&[0x00, 0x00, 0x20, 0x40]); // tau1 = 2.5
    b
}

#[test]
fn xarm_real_report_parses_hand_written_bytes_and_round_trips() {
    let b = real_report_bytes();
    let r = Report::parse(&b, ReportKind::Real).unwrap();
    assert_eq!((r.state, r.mode, r.cmd_num), (2, 1, 5));
    assert_eq!(r.angles[0], 0.5);
    assert_eq!(r.angles[6], -1.0);
    assert_eq!(r.pose[0], 200.0);
    assert_eq!(r.torques[0], 2.5);
    assert_eq!((r.error, r.warning), (0, 0));
    assert_eq!(r.encode(ReportKind::Real, 87).unwrap(), b);
}

#[test]
fn xarm_normal_report_carries_error_and_warning_at_89_and_90() {
    let mut b = real_report_bytes();
    b.resize(133, 0);
    b[..4].copy_from_slice(&[0x00, 0x00, 0x00, 0x85]); // 133
    b[89] = 22;
    b[90] = 11;
    let r = Report::parse(&b, ReportKind::Normal).unwrap();
    assert_eq!((r.error, r.warning), (22, 11));
    assert_eq!(r.encode(ReportKind::Normal, 133).unwrap(), b);
}

#[test]
fn xarm_report_buffer_locks_the_size_and_rejects_a_change() {
    let b = real_report_bytes();
    let mut rb = ReportBuf::new(ReportKind::Real);
    rb.push(&b[..50]);
    assert!(rb.next_report().unwrap().is_none());
    rb.push(&b[50..]);
    rb.push(&b);
    assert!(rb.next_report().unwrap().is_some());
    assert!(rb.next_report().unwrap().is_some());
    assert_eq!(rb.size(), Some(87));
    let mut other = b.clone();
    other[3] = 0x58;
    other.push(0);
    rb.push(&other);
    assert!(matches!(
        rb.next_report(),
        Err(Error::XArmReportSize {
            expected: 87,
            got: 88
        })
    ));
}

#[test]
fn xarm_report_buffer_rejects_a_tiny_size_header() {
    let mut rb = ReportBuf::new(ReportKind::Real);
    rb.push(&[0, 0, 0, 4, 1, 2, 3]);
    assert!(matches!(
        rb.next_report(),
        Err(Error::XArmReportSize { got: 4, .. })
    ));
}

// ---------------------------------------------------------------------------------------------
// XHand frames
// ---------------------------------------------------------------------------------------------

#[test]
fn crc16_xmodem_check_value() {
    // The catalogue check value of CRC-16/XMODEM.
    assert_eq!(crc16_xmodem(b"123456789"), 0x31c3);
    assert_eq!(crc16_xmodem(&[]), 0);
}

#[test]
fn xhand_version_request_and_reply_frames() {
    let req = Frame {
        src: 0xfe,
        dst: 0x00,
        cmd: consts::CMD_VERSION,
        payload: vec![],
    };
    assert_eq!(
        req.encode().unwrap(),
        [0x55, 0xaa, 0xfe, 0x00, 0x13, 0x00, 0x00, 0xd7, 0x1e]
    );
    let rep = [
        0x55, 0xaa, 0x00, 0xfe, 0x13, 0x03, 0x00, b'v', b'1', b'2', 0x91, 0xbe,
    ];
    let f = Frame::decode(&rep).unwrap();
    assert_eq!(
        (f.src, f.dst, f.cmd, f.payload.as_slice()),
        (0, 0xfe, 0x13, &b"v12"[..])
    );
    let read = Frame {
        src: 0xfe,
        dst: 0x00,
        cmd: consts::CMD_READ_STATE,
        payload: vec![],
    };
    assert_eq!(
        read.encode().unwrap(),
        [0x55, 0xaa, 0xfe, 0x00, 0x01, 0x00, 0x00, 0xd4, 0x33]
    );
}

#[test]
fn xhand_wrong_crc_is_named() {
    let rep = [
        0x55, 0xaa, 0x00, 0xfe, 0x13, 0x03, 0x00, b'v', b'1', b'2', 0x92, 0xbe,
    ];
    let e = Frame::decode(&rep).unwrap_err();
    assert!(
        matches!(
            e,
            Error::XHandCrc {
                command: 0x13,
                got: 0xbe92,
                computed: 0xbe91
            }
        ),
        "{e}"
    );
}

#[test]
fn xhand_finger_command_layout() {
    let c = FingerCommand {
        id: 3,
        kp: 100,
        ki: -1,
        kd: 2,
        position: 1.0,
        tor_max: 300,
        mode: 3,
    };
    let mut b = [0xffu8; 24];
    c.write(&mut b);
    assert_eq!(
        b,
        [
            0x03, 0x00, // id
            0x64, 0x00, // kp 100
            0xff, 0xff, // ki -1
            0x02, 0x00, // kd 2
            0x00, 0x00, 0x80, 0x3f, // position 1.0 f32 LE
            0x2c, 0x01, // tor_max 300
            0x03, 0x00, // mode 3
            0, 0, 0, 0, 0, 0, 0, 0 // reserved
        ]
    );
    assert_eq!(FingerCommand::read(&b), c);
}

#[test]
fn xhand_hand_command_is_288_bytes_and_round_trips() {
    let mut cmds = [FingerCommand {
        id: 0,
        kp: 100,
        ki: 0,
        kd: 0,
        position: 0.0,
        tor_max: 300,
        mode: 3,
    }; 12];
    for (i, c) in cmds.iter_mut().enumerate() {
        c.id = i as u16;
        c.position = i as f32 * 0.1;
    }
    let p = encode_hand_command(&cmds);
    assert_eq!(p.len(), 288);
    assert_eq!(&p[24..26], &[0x01, 0x00]); // second finger's id
    assert_eq!(decode_hand_command(&p).unwrap(), cmds);
    let frame = Frame {
        src: 0xfe,
        dst: 0,
        cmd: consts::CMD_SET_COMMAND,
        payload: p,
    }
    .encode()
    .unwrap();
    assert_eq!(&frame[..7], &[0x55, 0xaa, 0xfe, 0x00, 0x02, 0x20, 0x01]); // len 288 LE
    assert_eq!(frame.len(), 7 + 288 + 2);
    assert!(decode_hand_command(&[0u8; 287]).is_err());
}

#[test]
fn xhand_state_payload_layout() {
    let mut s = HandState::default();
    s.fingers[0] = FingerState {
        id: 0,
        sensor_id: 1,
        position: 0.5,
        torque: -2.0,
        raw_position: 7,
        temperature: 40,
        errors: [0, 9, 0],
    };
    s.tip_force[4] = [-3, 2, 200];
    let p = s.encode();
    assert_eq!(p.len(), 2208);
    assert_eq!(
        &p[..24],
        &[
            0x00, 0x00, 0x01, 0x00, // id, sensor id
            0x00, 0x00, 0x00, 0x3f, // position 0.5
            0x00, 0x00, 0x00, 0xc0, // torque -2.0
            0x07, 0x00, 0x00, 0x00, // raw position 7
            0x28, 0x00, // temperature 40
            0x00, 0x00, 0x09, 0x00, 0x00, 0x00 // errors
        ]
    );
    let tip4 = 288 + 4 * 384;
    assert_eq!(&p[tip4..tip4 + 3], &[0xfd, 0x02, 0xc8]);
    let d = HandState::decode(&p).unwrap();
    assert_eq!(d, s);
    let mut v = [0f32; 39];
    d.write_vector(&mut v);
    assert_eq!(v[0], 0.5);
    assert_eq!(v[12], -2.0);
    assert_eq!(
        &v[36..39],
        &[
            -3.0 * consts::TIP_FORCE_SCALE,
            2.0 * consts::TIP_FORCE_SCALE,
            200.0 * consts::TIP_FORCE_SCALE
        ]
    );
    assert!(matches!(
        HandState::decode(&p[..2207]),
        Err(Error::XHandReply { .. })
    ));
}

#[test]
fn xhand_parser_skips_garbage_and_survives_split_reads() {
    let f = Frame {
        src: 0,
        dst: 0xfe,
        cmd: 0x13,
        payload: b"abc".to_vec(),
    };
    let bytes = f.encode().unwrap();
    let mut p = FrameParser::new();
    p.push(&[0x00, 0x13, 0x55, 0x01, 0x55]);
    assert!(p.next_frame().is_none());
    p.push(&bytes[..4]);
    assert!(p.next_frame().is_none());
    p.push(&bytes[4..]);
    assert_eq!(p.next_frame().unwrap().unwrap(), f);
    assert!(p.next_frame().is_none());
    assert_eq!(p.dropped(), 5);
}

#[test]
fn xhand_parser_reports_a_bad_crc_and_resyncs_on_the_next_frame() {
    let good = Frame {
        src: 0,
        dst: 0xfe,
        cmd: 0x13,
        payload: vec![1, 2],
    }
    .encode()
    .unwrap();
    let mut bad = good.clone();
    let n = bad.len();
    bad[n - 1] ^= 0xff;
    let mut p = FrameParser::new();
    p.push(&bad);
    p.push(&good);
    assert!(matches!(p.next_frame(), Some(Err(Error::XHandCrc { .. }))));
    let mut got = None;
    while let Some(r) = p.next_frame() {
        if let Ok(f) = r {
            got = Some(f);
        }
    }
    assert_eq!(got.unwrap().payload, vec![1, 2]);
}

// ---------------------------------------------------------------------------------------------
// Fuzzing: parsers never panic; encoders and decoders agree
// ---------------------------------------------------------------------------------------------

proptest! {
    #![proptest_config(pir2_tests::fuzz_cases(256, "proptest-regressions/frames.txt"))]

    #[test]
    fn xarm_decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
        let _ = Command::decode(&bytes);
        let _ = Reply::decode(&bytes);
        let _ = Report::parse(&bytes, ReportKind::Real);
        let _ = Report::parse(&bytes, ReportKind::Normal);
        let _ = Report::parse(&bytes, ReportKind::Rich);
        let mut fb = FrameBuf::new();
        fb.push(&bytes);
        for _ in 0..64 {
            match fb.next_frame() {
                Ok(Some(f)) => { let _ = Reply::decode(&f); }
                _ => break,
            }
        }
    }

    #[test]
    fn xarm_report_buffer_never_panics(chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..300), 0..6),
                                      kind in 0usize..3) {
        let kind = [ReportKind::Real, ReportKind::Normal, ReportKind::Rich][kind];
        let mut rb = ReportBuf::new(kind);
        for c in chunks {
            rb.push(&c);
            for _ in 0..8 {
                match rb.next_report() { Ok(Some(_)) => {}, _ => break }
            }
        }
    }

    #[test]
    fn xhand_parser_never_panics(chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..300), 0..6)) {
        let mut p = FrameParser::new();
        for c in chunks {
            p.push(&c);
            for _ in 0..400 {
                if p.next_frame().is_none() { break; }
            }
        }
        let _ = HandState::decode(&[0u8; 10]);
    }

    #[test]
    fn xhand_parser_with_sync_heavy_input_never_panics(bytes in proptest::collection::vec(prop_oneof![Just(0x55u8), Just(0xaa), any::<u8>()], 0..400)) {
        let mut p = FrameParser::new();
        p.push(&bytes);
        for _ in 0..500 {
            if p.next_frame().is_none() { break; }
        }
    }

    #[test]
    fn xarm_command_round_trip(tid in any::<u16>(), register in any::<u8>(), params in proptest::collection::vec(any::<u8>(), 0..64)) {
        let c = Command { tid, proto: 2, register, params };
        let b = c.encode().unwrap();
        prop_assert_eq!(Command::decode(&b).unwrap(), c);
    }

    #[test]
    fn xarm_reply_round_trip_through_a_split_stream(tid in any::<u16>(), status in any::<u8>(),
                                                   data in proptest::collection::vec(any::<u8>(), 0..64),
                                                   cut in 0usize..80) {
        let r = Reply { tid, proto: 2, register: 42, status, data };
        let b = r.encode().unwrap();
        let cut = cut.min(b.len());
        let mut fb = FrameBuf::new();
        fb.push(&b[..cut]);
        let early = fb.next_frame().unwrap();
        prop_assert!(early.is_none() || cut == b.len());
        fb.push(&b[cut..]);
        let f = early.or_else(|| fb.next_frame().unwrap()).unwrap();
        prop_assert_eq!(Reply::decode(&f).unwrap(), r);
    }

    #[test]
    fn xhand_frame_round_trip_and_single_bit_flips_are_caught(src in any::<u8>(), cmd in any::<u8>(),
                                                             payload in proptest::collection::vec(any::<u8>(), 0..64),
                                                             bit in 0usize..8, at in any::<prop::sample::Index>()) {
        let f = Frame { src, dst: 0xfe, cmd, payload };
        let b = f.encode().unwrap();
        prop_assert_eq!(Frame::decode(&b).unwrap(), f.clone());
        // Flip one bit after the length field: the CRC must catch it.
        let mut c = b.clone();
        let i = 7 + at.index(c.len() - 7);
        c[i] ^= 1 << bit;
        prop_assert!(Frame::decode(&c).is_err());
    }

    #[test]
    fn report_round_trip(angles in proptest::array::uniform7(-10f32..10.0), torques in proptest::array::uniform7(-50f32..50.0),
                         state in 0u8..10, mode in 0u8..12, error in any::<u8>()) {
        // (The SDK refuses normal/rich reports with state >= 10 or mode >= 12.)
        let r = Report { size: 133, state, mode, cmd_num: 3, angles, pose: [0.0; 6], torques, error, ..Report::default() };
        let b = r.encode(ReportKind::Normal, 133).unwrap();
        prop_assert_eq!(Report::parse(&b, ReportKind::Normal).unwrap(), r);
    }
}
