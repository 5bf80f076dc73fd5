//! Camera sources for the slow channel.
//!
//! [`FolderCamera`] replays recorded frames: every `.png`, `.jpg` or `.jpeg` file of a
//! directory, in file-name order, one per `period`, stamped with the runtime clock when it is
//! delivered, as HWC `u8` RGB (grey and RGBA files are converted). It stands in for a live
//! camera in tests and replays through the same [`SlowSource`] trait. A file that cannot be
//! decoded is one error naming it (the run's stale-slow stop then stops the robot); at the end
//! of the folder the replay starts again from the first frame, or ends with an error when
//! built with [`FolderCamera::once`].

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, SlowFrame, SlowSource};

use crate::error::{Error, Result};

/// A directory of recorded frames replayed as a camera (see the module docs).
pub struct FolderCamera {
    files: Vec<PathBuf>,
    next: usize,
    repeat: bool,
    period: Duration,
    clock: Arc<dyn Clock>,
    delivered: Arc<AtomicU64>,
}

impl std::fmt::Debug for FolderCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FolderCamera")
            .field("frames", &self.files.len())
            .field("next", &self.next)
            .field("period", &self.period)
            .field("delivered", &self.delivered.load(Ordering::Relaxed))
            .finish_non_exhaustive()
    }
}

/// The image files of `dir` in file-name order.
fn frame_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io("frames", e))?;
    let mut files: Vec<PathBuf> = rd
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                    matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg")
                })
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(Error::io(
            "frames",
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("{} holds no .png, .jpg or .jpeg frame", dir.display()),
            ),
        ));
    }
    Ok(files)
}

impl FolderCamera {
    /// Replay the frames of `dir`, one per `period`, looping.
    pub fn open(dir: &Path, period: Duration, clock: Arc<dyn Clock>) -> Result<Self> {
        Ok(Self {
            files: frame_files(dir)?,
            next: 0,
            repeat: true,
            period,
            clock,
            delivered: Arc::new(AtomicU64::new(0)),
        })
    }

    /// Play the folder once: after the last frame, `capture` is an error.
    pub fn once(mut self) -> Self {
        self.repeat = false;
        self
    }

    /// Frames in the folder.
    pub fn len(&self) -> usize {
        self.files.len()
    }

    /// Whether the folder holds no frame (never: `open` refuses an empty folder).
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// Frames delivered so far.
    pub fn delivered(&self) -> u64 {
        self.delivered.load(Ordering::Relaxed)
    }

    /// The delivered-frames counter (shared; keep it before handing the camera to a run).
    pub fn frames(&self) -> Arc<AtomicU64> {
        self.delivered.clone()
    }

    /// Decode one frame file into HWC `u8` RGB.
    pub fn decode(path: &Path) -> pir2_runtime::Result<(Vec<u8>, (usize, usize))> {
        let img = image::open(path).map_err(|e| pir2_runtime::Error::Io {
            device: "frames".into(),
            message: format!("cannot decode {}: {e}", path.display()),
        })?;
        let rgb = img.to_rgb8();
        let (w, h) = rgb.dimensions();
        Ok((rgb.into_raw(), (h as usize, w as usize)))
    }
}

#[async_trait::async_trait]
impl SlowSource for FolderCamera {
    async fn capture(&mut self) -> pir2_runtime::Result<SlowFrame> {
        if self.next == self.files.len() {
            if !self.repeat {
                return Err(pir2_runtime::Error::Io {
                    device: "frames".into(),
                    message: format!("replay ended after {} frames", self.files.len()),
                });
            }
            self.next = 0;
        }
        std::thread::sleep(self.period);
        let (image, image_hw) = Self::decode(&self.files[self.next])?;
        self.next += 1;
        self.delivered.fetch_add(1, Ordering::Relaxed);
        Ok(SlowFrame::image(self.clock.now(), image, image_hw))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pir2_runtime::MockClock;

    fn block_on<F: std::future::Future>(f: F) -> F::Output {
        // The source never awaits anything pending: one poll completes it.
        let waker = std::task::Waker::noop();
        let mut cx = std::task::Context::from_waker(waker);
        let mut f = std::pin::pin!(f);
        match f.as_mut().poll(&mut cx) {
            std::task::Poll::Ready(v) => v,
            std::task::Poll::Pending => panic!("capture did not complete"),
        }
    }

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("pir2-frames-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn frames_replay_in_name_order_as_rgb_and_loop() {
        let d = dir("order");
        // Written out of order; a grey frame and an RGBA frame are converted to RGB.
        image::RgbImage::from_pixel(4, 2, image::Rgb([1, 2, 3]))
            .save(d.join("b.png"))
            .unwrap();
        image::GrayImage::from_pixel(3, 5, image::Luma([9]))
            .save(d.join("a.png"))
            .unwrap();
        image::RgbaImage::from_pixel(2, 2, image::Rgba([7, 8, 9, 255]))
            .save(d.join("c.png"))
            .unwrap();
        std::fs::write(d.join("notes.txt"), "not a frame").unwrap();
        let clock = Arc::new(MockClock::new());
        let mut cam = FolderCamera::open(&d, Duration::ZERO, clock).unwrap();
        assert_eq!(cam.len(), 3);
        let f = block_on(cam.capture()).unwrap();
        assert_eq!(
            (f.views[0].hw, &f.views[0].image[..3]),
            ((5, 3), &[9u8, 9, 9][..])
        );
        let f = block_on(cam.capture()).unwrap();
        assert_eq!((f.views[0].hw, f.views[0].image.len()), ((2, 4), 24));
        assert_eq!(&f.views[0].image[..3], &[1, 2, 3]);
        let f = block_on(cam.capture()).unwrap();
        assert_eq!(&f.views[0].image[..3], &[7, 8, 9]);
        let f = block_on(cam.capture()).unwrap();
        assert_eq!(f.views[0].hw, (5, 3), "loops to the first frame");
        assert_eq!(cam.delivered(), 4);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn an_empty_folder_a_bad_frame_and_the_end_of_a_single_pass_are_errors() {
        let d = dir("bad");
        let clock: Arc<dyn Clock> = Arc::new(MockClock::new());
        let e = FolderCamera::open(&d, Duration::ZERO, clock.clone()).unwrap_err();
        assert!(e.to_string().contains("no .png"), "{e}");
        std::fs::write(d.join("0.png"), "not a png").unwrap();
        let mut cam = FolderCamera::open(&d, Duration::ZERO, clock.clone()).unwrap();
        let e = block_on(cam.capture()).unwrap_err();
        assert!(e.to_string().contains("0.png"), "{e}");
        std::fs::remove_file(d.join("0.png")).unwrap();
        image::RgbImage::new(2, 2).save(d.join("1.png")).unwrap();
        let mut cam = FolderCamera::open(&d, Duration::ZERO, clock)
            .unwrap()
            .once();
        assert!(block_on(cam.capture()).is_ok());
        let e = block_on(cam.capture()).unwrap_err();
        assert!(e.to_string().contains("replay ended"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
