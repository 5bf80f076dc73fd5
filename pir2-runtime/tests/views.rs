//! Several camera views as one slow source ([`Views`]): frames come in source order with the
//! oldest capture time, and one failing or imageless view fails the whole frame.

use pir2_runtime::realtime::block_on;
use pir2_runtime::{Nanos, Result, SlowFrame, SlowSource, Views};

/// Frames of one fixed-size image filled with `fill`, captured at `t`, `t + step`, ...
struct Scripted {
    fill: u8,
    t: Nanos,
    step: Nanos,
    fail_at: Option<usize>,
    n: usize,
    empty: bool,
}

#[async_trait::async_trait]
impl SlowSource for Scripted {
    async fn capture(&mut self) -> Result<SlowFrame> {
        self.n += 1;
        if self.fail_at == Some(self.n) {
            return Err(pir2_runtime::Error::Io {
                device: format!("cam{}", self.fill),
                message: "unplugged".into(),
            });
        }
        let t = self.t + self.step * (self.n as Nanos - 1);
        if self.empty {
            return Ok(SlowFrame {
                t_capture: t,
                ..Default::default()
            });
        }
        let mut f = SlowFrame::image(t, vec![self.fill; 2 * 3 * 3], (2, 3));
        f.values = vec![f32::from(self.fill)];
        Ok(f)
    }
}

fn cam(fill: u8, t: Nanos) -> Scripted {
    Scripted {
        fill,
        t,
        step: 100,
        fail_at: None,
        n: 0,
        empty: false,
    }
}

#[test]
fn views_come_in_source_order_with_the_oldest_capture_time() {
    let mut v = Views::new(vec![cam(1, 5_000), cam(2, 4_000), cam(3, 6_000)]).unwrap();
    assert_eq!(v.len(), 3);
    let f = block_on(v.capture()).unwrap();
    let fills: Vec<u8> = f.views.iter().map(|v| v.image[0]).collect();
    assert_eq!(fills, [1, 2, 3]);
    assert!(f.views.iter().all(|v| v.hw == (2, 3)));
    assert_eq!(f.t_capture, 4_000, "the stalest view's time");
    assert_eq!(f.values, [1.0, 2.0, 3.0]);
    let f = block_on(v.capture()).unwrap();
    assert_eq!(f.t_capture, 4_100);
}

#[test]
fn a_failing_or_imageless_view_fails_the_whole_frame() {
    let mut bad = cam(2, 0);
    bad.fail_at = Some(2);
    let mut v = Views::new(vec![cam(1, 0), bad]).unwrap();
    assert!(block_on(v.capture()).is_ok());
    let e = block_on(v.capture()).unwrap_err().to_string();
    assert!(e.contains("cam2") && e.contains("unplugged"), "{e}");

    let mut empty = cam(9, 0);
    empty.empty = true;
    let mut v = Views::new(vec![cam(1, 0), empty]).unwrap();
    let e = block_on(v.capture()).unwrap_err().to_string();
    assert!(
        e.contains("camera view 1") && e.contains("without an image"),
        "{e}"
    );

    assert!(Views::<Scripted>::new(Vec::new()).is_err());
}
