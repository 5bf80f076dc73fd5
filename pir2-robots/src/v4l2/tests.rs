//! The capture loop over a scripted fake device, and the pixel conversions against OpenCV.

use std::collections::VecDeque;

use pir2_runtime::MockClock;

use super::*;

const MS: u64 = 1_000_000;
/// The fake's `CLOCK_MONOTONIC` (unrelated to the runtime clock's epoch, as on a robot).
const MONO: u64 = 5_000 * MS;
/// The runtime clock when frames are dequeued.
const NOW: u64 = 100 * MS;

#[derive(Debug, Clone)]
struct FakeFrame {
    bytes: Vec<u8>,
    flags: u32,
    ts: u64,
    seq: u32,
}

#[derive(Debug, Clone)]
enum Ready {
    Frame(FakeFrame),
    Errno(i32),
}

#[derive(Debug)]
enum Step {
    /// `wait` returns Ready after these become dequeueable.
    Arrive(Vec<Ready>),
    /// `wait` fails with this errno.
    WaitErrno(i32),
    /// `wait` reports POLLERR.
    WaitFailed,
}

/// A device with `n` buffers whose `wait`s follow a script (then time out).
struct Fake {
    steps: VecDeque<Step>,
    ready: VecDeque<Result<Dequeued, i32>>,
    buffers: Vec<Vec<u8>>,
    queued: Vec<bool>,
    mono: u64,
}

impl Fake {
    fn new(n: usize, ready: Vec<Ready>, steps: Vec<Step>) -> Self {
        let mut f = Fake {
            steps: steps.into(),
            ready: VecDeque::new(),
            buffers: vec![Vec::new(); n],
            queued: vec![true; n],
            mono: MONO,
        };
        f.arrive(ready);
        f
    }

    fn arrive(&mut self, ready: Vec<Ready>) {
        for r in ready {
            match r {
                Ready::Errno(e) => self.ready.push_back(Err(e)),
                Ready::Frame(fr) => {
                    let index = self
                        .queued
                        .iter()
                        .position(|&q| q)
                        .expect("a queued buffer");
                    self.queued[index] = false;
                    self.buffers[index] = fr.bytes.clone();
                    self.ready.push_back(Ok(Dequeued {
                        index: index as u32,
                        bytesused: fr.bytes.len() as u32,
                        flags: fr.flags,
                        sequence: fr.seq,
                        timestamp_ns: fr.ts,
                    }));
                }
            }
        }
    }

    /// Every buffer is back with the driver.
    fn all_queued(&self) -> bool {
        self.queued.iter().all(|&q| q) && self.ready.is_empty()
    }
}

impl Device for Fake {
    fn wait(&mut self, timeout: Duration) -> io::Result<Wait> {
        match self.steps.pop_front() {
            Some(Step::Arrive(r)) => {
                self.mono += MS;
                self.arrive(r);
                Ok(Wait::Ready)
            }
            Some(Step::WaitErrno(e)) => Err(io::Error::from_raw_os_error(e)),
            Some(Step::WaitFailed) => Ok(Wait::Failed),
            None => {
                self.mono += timeout.as_nanos() as u64;
                Ok(Wait::TimedOut)
            }
        }
    }
    fn dequeue(&mut self) -> io::Result<Option<Dequeued>> {
        match self.ready.pop_front() {
            None => Ok(None),
            Some(Ok(b)) => Ok(Some(b)),
            Some(Err(e)) => Err(io::Error::from_raw_os_error(e)),
        }
    }
    fn requeue(&mut self, index: u32) -> io::Result<()> {
        let q = &mut self.queued[index as usize];
        assert!(!*q, "buffer {index} queued twice");
        *q = true;
        Ok(())
    }
    fn data(&self, index: u32, len: usize) -> &[u8] {
        let b = &self.buffers[index as usize];
        &b[..len.min(b.len())]
    }
    fn monotonic_ns(&self) -> u64 {
        self.mono
    }
}

const MONOTONIC: u32 = sys::BUF_FLAG_TIMESTAMP_MONOTONIC;

/// A 4x2 YUYV frame of one grey level `y` (U = V = 128).
fn grey(y: u8, age_ms: u64, seq: u32) -> Ready {
    Ready::Frame(FakeFrame {
        bytes: [y, 128, y, 128].repeat(4),
        flags: MONOTONIC,
        ts: MONO - age_ms * MS,
        seq,
    })
}

fn yuyv_4x2() -> Negotiated {
    Negotiated {
        format: PixelFormat::Yuyv,
        width: 4,
        height: 2,
        bytesperline: 8,
        sizeimage: 16,
    }
}

fn capture(fake: Fake, format: Negotiated) -> (Capture<Fake>, MockClock) {
    let clock = MockClock::new();
    clock.set(NOW);
    let cap = Capture::new(
        fake,
        "/dev/video9".into(),
        format,
        Duration::from_secs(1),
        Arc::new(clock.clone()),
    );
    (cap, clock)
}

/// The RGB of a grey YUYV level (BT.601 limited range).
fn rgb_of(y: u8) -> u8 {
    ((y as f64 - 16.0) * 1.164).round().clamp(0.0, 255.0) as u8
}

#[test]
fn driver_timestamps_give_the_capture_time_on_the_runtime_clock_and_the_newest_frame_wins() {
    // Two frames already waiting (a slow backbone): the older is skipped and queued back.
    let fake = Fake::new(
        4,
        vec![grey(60, 50, 1), grey(200, 30, 2)],
        vec![Step::Arrive(vec![grey(120, 9, 3)])],
    );
    let (mut cap, clock) = capture(fake, yuyv_4x2());
    let f = cap.next_frame().unwrap();
    // Captured 30 ms before the dequeue: 100 ms − 30 ms on the runtime clock.
    assert_eq!(f.t_capture, NOW - 30 * MS);
    assert_eq!(f.views[0].hw, (2, 4));
    assert_eq!(f.views[0].image, vec![rgb_of(200); 24]);
    assert_eq!(cap.counters.skipped.load(Ordering::Relaxed), 1);
    assert!(cap.dev.all_queued());
    assert_eq!(cap.timestamps, Some(Timestamps::Driver));
    // The next frame arrives during the wait (the fake's monotonic clock moves 1 ms).
    clock.set(NOW + 40 * MS);
    let f = cap.next_frame().unwrap();
    assert_eq!(f.t_capture, NOW + 40 * MS - (MS + 9 * MS));
    assert_eq!(f.views[0].image[0], rgb_of(120));
    assert_eq!(cap.counters.delivered.load(Ordering::Relaxed), 2);
    assert!(cap.dev.all_queued());
    // The mapping itself: age = monotonic now − stamp; a stamp from the future is age 0.
    assert_eq!(monotonic_to_runtime(7 * MS, 10 * MS, 50 * MS), 47 * MS);
    assert_eq!(monotonic_to_runtime(11 * MS, 10 * MS, 50 * MS), 50 * MS);
    assert_eq!(monotonic_to_runtime(0, 10 * MS, 5 * MS), 0);
}

#[test]
fn without_monotonic_stamps_the_dequeue_time_is_used() {
    let Ready::Frame(mut fr) = grey(90, 500, 1) else {
        unreachable!()
    };
    fr.flags = 0; // V4L2_BUF_FLAG_TIMESTAMP_UNKNOWN
    let (mut cap, _) = capture(Fake::new(2, vec![Ready::Frame(fr)], vec![]), yuyv_4x2());
    let f = cap.next_frame().unwrap();
    assert_eq!(f.t_capture, NOW);
    assert_eq!(cap.timestamps, Some(Timestamps::Dequeue));
}

#[test]
fn eintr_is_retried_and_flagged_buffers_are_dropped() {
    let Ready::Frame(mut flagged) = grey(10, 20, 1) else {
        unreachable!()
    };
    flagged.flags |= sys::BUF_FLAG_ERROR;
    let fake = Fake::new(
        3,
        vec![Ready::Errno(libc::EINTR)],
        vec![
            Step::WaitErrno(libc::EINTR),
            Step::Arrive(vec![Ready::Frame(flagged)]),
            Step::Arrive(vec![Ready::Errno(libc::EINTR), grey(150, 5, 2)]),
        ],
    );
    let (mut cap, _) = capture(fake, yuyv_4x2());
    let f = cap.next_frame().unwrap();
    assert_eq!(f.views[0].image[0], rgb_of(150));
    assert_eq!(cap.counters.flagged.load(Ordering::Relaxed), 1);
    assert!(cap.dev.all_queued());
}

#[test]
fn a_timeout_a_vanished_device_and_a_failed_poll_are_errors_naming_the_device() {
    let (mut cap, _) = capture(Fake::new(2, vec![], vec![]), yuyv_4x2());
    let e = cap.next_frame().unwrap_err();
    assert!(
        matches!(
            e,
            Error::CameraTimeout {
                waited_ms: 1000,
                ..
            }
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains("/dev/video9"), "{e}");

    let fake = Fake::new(
        2,
        vec![],
        vec![Step::Arrive(vec![Ready::Errno(libc::ENODEV)])],
    );
    let (mut cap, _) = capture(fake, yuyv_4x2());
    let e = cap.next_frame().unwrap_err();
    assert!(matches!(e, Error::CameraGone { .. }), "{e:?}");
    assert!(
        e.to_string().contains("/dev/video9: device disappeared"),
        "{e}"
    );

    // EIO: UVC marks its queue failed when the camera is unplugged.
    let fake = Fake::new(2, vec![], vec![Step::Arrive(vec![Ready::Errno(libc::EIO)])]);
    let (mut cap, _) = capture(fake, yuyv_4x2());
    assert!(matches!(
        cap.next_frame().unwrap_err(),
        Error::CameraGone { .. }
    ));

    let (mut cap, _) = capture(Fake::new(2, vec![], vec![Step::WaitFailed]), yuyv_4x2());
    assert!(matches!(
        cap.next_frame().unwrap_err(),
        Error::CameraGone { .. }
    ));

    let fake = Fake::new(2, vec![], vec![Step::WaitErrno(libc::EBADF)]);
    let (mut cap, _) = capture(fake, yuyv_4x2());
    let e = cap.next_frame().unwrap_err();
    assert!(matches!(e, Error::CameraIo { op: "poll", .. }), "{e:?}");

    // A frame already held when the device vanishes goes back before the error.
    let fake = Fake::new(2, vec![grey(1, 1, 1), Ready::Errno(libc::ENODEV)], vec![]);
    let (mut cap, _) = capture(fake, yuyv_4x2());
    assert!(matches!(
        cap.next_frame().unwrap_err(),
        Error::CameraGone { .. }
    ));
    assert!(cap.dev.queued.iter().all(|&q| q));
    assert_eq!(cap.counters.delivered.load(Ordering::Relaxed), 0);
}

#[test]
fn a_stale_short_or_corrupt_frame_is_an_error_and_its_buffer_goes_back() {
    // The same capture time twice: the second is not a new frame.
    let fake = Fake::new(
        2,
        vec![grey(30, 10, 1)],
        vec![Step::Arrive(vec![grey(40, 10, 2)])],
    );
    let (mut cap, _) = capture(fake, yuyv_4x2());
    cap.next_frame().unwrap();
    let e = cap.next_frame().unwrap_err();
    assert!(matches!(e, Error::CameraFrame { sequence: 2, .. }), "{e:?}");
    assert!(
        e.to_string().contains("not after the previous frame"),
        "{e}"
    );
    assert!(cap.dev.all_queued());

    // A short YUYV buffer.
    let short = Ready::Frame(FakeFrame {
        bytes: vec![16; 10],
        flags: MONOTONIC,
        ts: MONO,
        seq: 7,
    });
    let (mut cap, _) = capture(Fake::new(2, vec![short], vec![]), yuyv_4x2());
    let e = cap.next_frame().unwrap_err();
    assert!(e.to_string().contains("short frame"), "{e}");
    assert!(cap.dev.all_queued());

    // A truncated MJPEG frame (the end of a real JPEG cut off).
    let jpeg = include_bytes!("../../tests/data/v4l2/mjpeg_48x32.jpg");
    let mjpeg = Negotiated {
        format: PixelFormat::Mjpeg,
        width: 48,
        height: 32,
        bytesperline: 0,
        sizeimage: 48 * 32 * 2,
    };
    let cut = Ready::Frame(FakeFrame {
        bytes: jpeg[..jpeg.len() / 2].to_vec(),
        flags: MONOTONIC,
        ts: MONO,
        seq: 8,
    });
    let whole = Ready::Frame(FakeFrame {
        bytes: jpeg.to_vec(),
        flags: MONOTONIC,
        ts: MONO + MS,
        seq: 9,
    });
    let fake = Fake::new(2, vec![cut], vec![Step::Arrive(vec![whole])]);
    let (mut cap, _) = capture(fake, mjpeg);
    let e = cap.next_frame().unwrap_err();
    assert!(matches!(e, Error::CameraFrame { sequence: 8, .. }), "{e:?}");
    assert!(e.to_string().contains("truncated JPEG"), "{e}");
    // The camera goes on with the next good frame.
    let f = cap.next_frame().unwrap();
    assert_eq!(
        (f.views[0].hw, f.views[0].image.len()),
        ((32, 48), 48 * 32 * 3)
    );
    assert!(cap.dev.all_queued());
}

/// Largest per-value difference of two equally long byte images.
fn max_diff(a: &[u8], b: &[u8]) -> u8 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
}

/// OpenCV's `COLOR_YUV2RGB_YUYV` (BT.601, limited range, 20-bit fixed point with the
/// coefficients 1.164, 1.596, −0.813, −0.391, 2.018) on the committed fixture
/// (`tests/data/v4l2/make_golden.py`, seeded random bytes plus a row of extremes, luma
/// below 16 included). Ours uses the same coefficients, rounding and black-level clamp, so
/// agreement is exact: tolerance 0. (Without the clamp of luma below 16 it differs by up to
/// 19 levels on 23 values of this fixture.)
#[test]
fn yuyv_to_rgb_matches_opencv_on_the_golden_fixture() {
    let yuyv = include_bytes!("../../tests/data/v4l2/yuyv_32x8.yuyv");
    let want = include_bytes!("../../tests/data/v4l2/yuyv_32x8.rgb");
    let mut got = Vec::new();
    convert::yuyv_to_rgb(yuyv, 32, 8, 64, &mut got).unwrap();
    assert_eq!(max_diff(&got, want), 0);
    // The same frame with padded rows (a driver's larger stride).
    let padded: Vec<u8> = yuyv
        .chunks(64)
        .flat_map(|r| [r, &[7u8; 6]].concat())
        .collect();
    let mut got = Vec::new();
    convert::yuyv_to_rgb(&padded, 32, 8, 70, &mut got).unwrap();
    assert_eq!(max_diff(&got, want), 0);
    let mut v = Vec::new();
    assert!(convert::yuyv_to_rgb(&yuyv[..500], 32, 8, 64, &mut v).is_err());
    assert!(convert::yuyv_to_rgb(yuyv, 31, 8, 64, &mut v).is_err());
}

/// The committed 4:2:2 JPEG decoded like OpenCV's `imdecode` (libjpeg-turbo) to within
/// [`MJPEG_TOLERANCE`], and identically when its Huffman tables are stripped as UVC cameras
/// send them (the standard tables are put back).
#[test]
fn mjpeg_decodes_like_opencv_with_or_without_huffman_tables() {
    let jpeg = include_bytes!("../../tests/data/v4l2/mjpeg_48x32.jpg");
    let nodht = include_bytes!("../../tests/data/v4l2/mjpeg_48x32_nodht.jpg");
    let want = include_bytes!("../../tests/data/v4l2/mjpeg_48x32.rgb");
    let mut full = Vec::new();
    convert::decode_mjpeg(jpeg, 48, 32, &mut full).unwrap();
    let d = max_diff(&full, want);
    eprintln!("MJPEG max difference to OpenCV: {d}");
    assert!(d <= MJPEG_TOLERANCE, "max difference to OpenCV {d}");
    let mut stripped = Vec::new();
    convert::decode_mjpeg(nodht, 48, 32, &mut stripped).unwrap();
    assert_eq!(stripped, full);
    // Padding after the end-of-image marker is allowed; a wrong size, no SOI, no EOI or a
    // damaged scan are refused.
    let mut padded = jpeg.to_vec();
    padded.extend_from_slice(&[0; 100]);
    let mut v = Vec::new();
    convert::decode_mjpeg(&padded, 48, 32, &mut v).unwrap();
    assert_eq!(v, full);
    let mut v = Vec::new();
    let e = convert::decode_mjpeg(jpeg, 64, 32, &mut v).unwrap_err();
    assert!(e.contains("48x32") && e.contains("64x32"), "{e}");
    assert!(convert::decode_mjpeg(&jpeg[2..], 48, 32, &mut v).is_err());
    assert!(convert::decode_mjpeg(&jpeg[..jpeg.len() - 2], 48, 32, &mut v).is_err());
    let mut header_cut = jpeg[..40].to_vec();
    header_cut.extend_from_slice(&[0xff, 0xd9]);
    assert!(convert::decode_mjpeg(&header_cut, 48, 32, &mut v).is_err());
}

/// `jpeg-decoder` and libjpeg-turbo use different integer IDCTs and chroma upsampling
/// rounding, so decoded values may differ by a few levels: 3 at most on this fixture
/// (measured with jpeg-decoder 0.3.2 against OpenCV 4.14's libjpeg-turbo); bounded at 4.
const MJPEG_TOLERANCE: u8 = 4;

#[test]
fn rgb24_rows_drop_the_row_padding() {
    let data: Vec<u8> = (0..2u8)
        .flat_map(|r| {
            let mut row: Vec<u8> = (0..6).map(|i| r * 10 + i).collect();
            row.extend_from_slice(&[99, 99]);
            row
        })
        .collect();
    let mut out = Vec::new();
    convert::rgb24_rows(&data, 2, 2, 8, &mut out).unwrap();
    assert_eq!(out, vec![0, 1, 2, 3, 4, 5, 10, 11, 12, 13, 14, 15]);
    assert!(convert::rgb24_rows(&data[..12], 2, 2, 8, &mut out).is_err());
}

/// A path that is no V4L2 node is one error naming it (no camera needed).
#[test]
fn opening_a_missing_or_non_v4l2_node_is_one_error_naming_it() {
    let clock: Arc<dyn Clock> = Arc::new(MockClock::new());
    let e =
        V4l2Camera::open(&V4l2Config::new("/dev/video-pir2-missing"), clock.clone()).unwrap_err();
    assert!(matches!(e, Error::CameraIo { op: "open", .. }), "{e:?}");
    assert!(e.to_string().contains("/dev/video-pir2-missing"), "{e}");
    let e = V4l2Camera::open(&V4l2Config::new("/dev/null"), clock).unwrap_err();
    assert!(matches!(e, Error::CameraUnsupported { .. }), "{e:?}");
    assert!(
        e.to_string().contains("/dev/null: not a V4L2 device"),
        "{e}"
    );
}
