//! A live USB (UVC) or other V4L2 camera as the slow channel's image source (Linux only).
//!
//! One file on purpose (the raw ioctl layer, negotiation and pixel conversion are the
//! submodules `sys`, `negotiate` and `convert`): the device's lifecycle (open, negotiate, map
//! buffers, stream, stop) is one state machine over one file descriptor, with one
//! buffer-ownership rule (every dequeued buffer goes back to the driver on every path),
//! checked in one place.
//!
//! [`V4l2Camera`] talks to `/dev/videoN` with the kernel's V4L2 ioctls directly (no
//! libv4l): it yields HWC `u8` RGB frames through [`SlowSource`], stamped with the time the
//! *driver* says the frame was captured, so that the slow channel's age (`d_vis`) counts
//! from the sensor, not from when pir2 happened to read the frame.
//!
//! # Opening and negotiation
//! [`V4l2Camera::open`] opens the node non-blocking and asks `VIDIOC_QUERYCAP` whether it
//! is a video capture node with streaming I/O (USB webcams also create a metadata node,
//! which is refused by name). It lists every pixel format (`VIDIOC_ENUM_FMT`) with its frame
//! sizes (`VIDIOC_ENUM_FRAMESIZES`), picks one with [`choose`] (RGB24, YUYV or MJPEG; the
//! asked size exactly, or the size nearest 640×480; the rules are in [`negotiate`]), asks
//! the driver for it with `VIDIOC_S_FMT`, and keeps what the driver answers (it may change
//! the size or the format; [`accept`] refuses an answer pir2 cannot convert). Nothing usable
//! is one [`Error::CameraFormat`] naming the device, the request and every format and size
//! the device offered.
//!
//! # Streaming
//! Memory-mapped streaming: `VIDIOC_REQBUFS` (4 buffers by default, at least 2),
//! `VIDIOC_QUERYBUF` + `mmap` per buffer, all queued (`VIDIOC_QBUF`), `VIDIOC_STREAMON`. A
//! capture waits with `poll` (bounded by [`V4l2Config::timeout`]) and dequeues *every* filled
//! buffer (`VIDIOC_DQBUF`), keeping only the newest and queueing the older ones back: a slow
//! backbone therefore always gets the latest frame, never a backlog. Buffers the driver
//! flags `V4L2_BUF_FLAG_ERROR` (an incomplete USB transfer) are queued back unread and
//! counted. The frame is converted to RGB ([`convert`]) and its buffer queued back. Dropping
//! the camera stops streaming (`VIDIOC_STREAMOFF`) and unmaps the buffers.
//!
//! # Capture timestamps
//! When a buffer carries `V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`, its `timestamp` is a
//! `CLOCK_MONOTONIC` time (for UVC: the start of the frame's exposure or its first USB
//! packet; other drivers stamp the end of the frame). It is mapped onto the runtime's
//! [`Clock`] by its age: right after dequeuing, `CLOCK_MONOTONIC` is read just before and
//! just after [`Clock::now`], and
//! `t_capture = now − (monotonic_mid − timestamp)` (saturating at 0, a timestamp "from the
//! future" counting as age 0). This needs only that the runtime clock runs at the rate of
//! `CLOCK_MONOTONIC`, which holds for [`pir2_runtime::SystemClock`] (built on
//! `std::time::Instant`, itself `CLOCK_MONOTONIC` on Linux), whatever its epoch; the
//! mapping's error is the time between the two `CLOCK_MONOTONIC` reads (well under a
//! microsecond). A driver whose buffers are not monotonic-stamped (`TIMESTAMP_UNKNOWN` or
//! `COPY`) gets the runtime clock at dequeue time instead, which makes frames look younger
//! than they are by the driver's and USB's latency; [`V4l2Camera::timestamps`] says which
//! source the last frame used.
//!
//! # Errors (fail closed)
//! Every failure is one typed error naming the device and no frame: a node that cannot be
//! opened or is not a streaming capture device, no usable format, no frame within the
//! timeout ([`Error::CameraTimeout`]), a device that disappeared (`ENODEV`, `EIO` from a
//! queue the driver marked failed, or `poll` reporting an error: [`Error::CameraGone`]), a frame that is truncated, corrupt, of
//! another size than negotiated, or not newer than the previous frame
//! ([`Error::CameraFrame`]). A stale frame is never returned as a new one. `EINTR` is
//! retried within the same timeout.

pub mod convert;
pub mod negotiate;
pub mod sys;

use std::fmt;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pir2_runtime::{Clock, Nanos, SlowFrame, SlowSource};

use crate::error::{Error, Result};
pub use negotiate::{
    accept, choose, parse_size, FormatRequest, FrameSizes, Negotiated, Offered, PixelFormat,
    DEFAULT_SIZE,
};

/// Options of [`V4l2Camera::open`].
#[derive(Debug, Clone)]
pub struct V4l2Config {
    /// The device node, e.g. `/dev/video0`.
    pub device: PathBuf,
    /// Pixel format and size to ask for (`None`s: let [`choose`] decide).
    pub request: FormatRequest,
    /// How long one capture may wait for a frame.
    pub timeout: Duration,
    /// Driver buffers to request (the driver may grant more or fewer; fewer than 2 is an
    /// error).
    pub buffers: u32,
}

impl V4l2Config {
    /// `device` with the defaults: any supported format near 640×480, 1 s timeout, 4
    /// buffers.
    pub fn new(device: impl Into<PathBuf>) -> Self {
        Self {
            device: device.into(),
            request: FormatRequest::default(),
            timeout: Duration::from_secs(1),
            buffers: 4,
        }
    }
}

/// Where a frame's `t_capture` came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timestamps {
    /// The driver's `CLOCK_MONOTONIC` buffer timestamp, mapped to the runtime clock.
    Driver,
    /// The runtime clock when the frame was dequeued (the driver's stamps are not
    /// monotonic).
    Dequeue,
}

/// Counters of a camera (shared: keep a handle before giving the camera to a run).
#[derive(Debug, Default)]
pub struct CameraCounters {
    /// Frames returned.
    pub delivered: Arc<AtomicU64>,
    /// Frames dequeued but replaced by a newer one in the same capture.
    pub skipped: AtomicU64,
    /// Buffers the driver flagged as corrupt, queued back unread.
    pub flagged: AtomicU64,
}

/// A buffer as dequeued from the driver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Dequeued {
    pub index: u32,
    pub bytesused: u32,
    pub flags: u32,
    pub sequence: u32,
    /// The buffer's `timestamp` in nanoseconds (its clock is given by `flags`).
    pub timestamp_ns: u64,
}

/// The outcome of waiting for a filled buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Wait {
    /// A buffer can be dequeued.
    Ready,
    /// Nothing within the time given.
    TimedOut,
    /// `poll` reported an error or hang-up on the node.
    Failed,
}

/// The device calls the capture loop makes (the real node, or a scripted fake in tests).
pub(crate) trait Device: Send {
    /// Wait up to `timeout` for a filled buffer (`EINTR` comes back as an error of kind
    /// `Interrupted`).
    fn wait(&mut self, timeout: Duration) -> io::Result<Wait>;
    /// Dequeue a filled buffer; `Ok(None)` when none is ready (`EAGAIN`).
    fn dequeue(&mut self) -> io::Result<Option<Dequeued>>;
    /// Give a dequeued buffer back to the driver.
    fn requeue(&mut self, index: u32) -> io::Result<()>;
    /// The first `len` bytes of buffer `index` (fewer if the buffer is shorter).
    fn data(&self, index: u32, len: usize) -> &[u8];
    /// `CLOCK_MONOTONIC` now, in nanoseconds.
    fn monotonic_ns(&self) -> u64;
}

/// A `CLOCK_MONOTONIC` timestamp `ts` on the runtime clock, given the runtime clock's `now`
/// and `CLOCK_MONOTONIC`'s `mono_now` read at the same moment (see the module docs).
pub fn monotonic_to_runtime(ts: u64, mono_now: u64, now: Nanos) -> Nanos {
    now.saturating_sub(mono_now.saturating_sub(ts))
}

/// An OS error of `op` as the crate's error: the device gone, or a failed call.
fn os_error(device: &str, op: &'static str, e: io::Error) -> Error {
    match e.raw_os_error() {
        // ENODEV/ENXIO: the node is gone; EIO: the driver put its queue in the error state,
        // which UVC does when the camera is unplugged.
        Some(libc::ENODEV) | Some(libc::ENXIO) | Some(libc::EIO) => Error::CameraGone {
            device: device.to_string(),
            reason: format!("{op}: {e}"),
        },
        _ => Error::CameraIo {
            device: device.to_string(),
            op,
            source: e,
        },
    }
}

/// The capture loop over a [`Device`] (see the module docs).
pub(crate) struct Capture<D> {
    dev: D,
    device: String,
    format: Negotiated,
    timeout: Duration,
    clock: Arc<dyn Clock>,
    last_ts: Option<u64>,
    timestamps: Option<Timestamps>,
    counters: Arc<CameraCounters>,
}

impl<D: Device> Capture<D> {
    pub(crate) fn new(
        dev: D,
        device: String,
        format: Negotiated,
        timeout: Duration,
        clock: Arc<dyn Clock>,
    ) -> Self {
        Self {
            dev,
            device,
            format,
            timeout,
            clock,
            last_ts: None,
            timestamps: None,
            counters: Arc::default(),
        }
    }

    fn requeue(&mut self, index: u32) -> Result<()> {
        self.dev
            .requeue(index)
            .map_err(|e| os_error(&self.device, "VIDIOC_QBUF", e))
    }

    /// Wait for filled buffers and keep the newest (older ones and flagged ones go back to
    /// the driver).
    fn newest(&mut self) -> Result<Dequeued> {
        let start = self.dev.monotonic_ns();
        let deadline = start.saturating_add(self.timeout.as_nanos() as u64);
        let mut newest: Option<Dequeued> = None;
        loop {
            loop {
                match self.dev.dequeue() {
                    Ok(Some(b)) if b.flags & sys::BUF_FLAG_ERROR != 0 => {
                        self.counters.flagged.fetch_add(1, Ordering::Relaxed);
                        self.requeue(b.index)?;
                    }
                    Ok(Some(b)) => {
                        if let Some(old) = newest.replace(b) {
                            self.counters.skipped.fetch_add(1, Ordering::Relaxed);
                            self.requeue(old.index)?;
                        }
                    }
                    Ok(None) => break,
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        if let Some(b) = newest {
                            let _ = self.dev.requeue(b.index);
                        }
                        return Err(os_error(&self.device, "VIDIOC_DQBUF", e));
                    }
                }
            }
            if let Some(b) = newest {
                return Ok(b);
            }
            let now = self.dev.monotonic_ns();
            let timed_out = Error::CameraTimeout {
                device: self.device.clone(),
                waited_ms: self.timeout.as_millis() as u64,
            };
            if now >= deadline {
                return Err(timed_out);
            }
            match self.dev.wait(Duration::from_nanos(deadline - now)) {
                Ok(Wait::Ready) => {}
                Ok(Wait::TimedOut) => return Err(timed_out),
                Ok(Wait::Failed) => {
                    return Err(Error::CameraGone {
                        device: self.device.clone(),
                        reason: "poll reported an error on the node".into(),
                    })
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(os_error(&self.device, "poll", e)),
            }
        }
    }

    /// The next frame (see the module docs).
    pub(crate) fn next_frame(&mut self) -> Result<SlowFrame> {
        let b = self.newest()?;
        let r = self.frame(&b);
        // The buffer goes back to the driver whatever the frame was.
        let q = self.requeue(b.index);
        let frame = r?;
        q?;
        self.counters.delivered.fetch_add(1, Ordering::Relaxed);
        Ok(frame)
    }

    fn frame(&mut self, b: &Dequeued) -> Result<SlowFrame> {
        let bad = |reason: String| Error::CameraFrame {
            device: self.device.clone(),
            sequence: b.sequence,
            reason,
        };
        let monotonic = b.flags & sys::BUF_FLAG_TIMESTAMP_MASK == sys::BUF_FLAG_TIMESTAMP_MONOTONIC;
        let t_capture = if monotonic {
            if let Some(last) = self.last_ts.filter(|&l| b.timestamp_ns <= l) {
                return Err(bad(format!(
                    "captured at {} ns, not after the previous frame ({last} ns)",
                    b.timestamp_ns
                )));
            }
            let before = self.dev.monotonic_ns();
            let now = self.clock.now();
            let after = self.dev.monotonic_ns();
            let mid = before + after.saturating_sub(before) / 2;
            monotonic_to_runtime(b.timestamp_ns, mid, now)
        } else {
            self.clock.now()
        };
        let f = self.format;
        let (w, h) = (f.width as usize, f.height as usize);
        let data = self.dev.data(b.index, b.bytesused as usize);
        let mut image = Vec::with_capacity(w * h * 3);
        let converted = match f.format {
            PixelFormat::Yuyv => {
                convert::yuyv_to_rgb(data, w, h, f.bytesperline as usize, &mut image)
            }
            PixelFormat::Rgb24 => {
                convert::rgb24_rows(data, w, h, f.bytesperline as usize, &mut image)
            }
            PixelFormat::Mjpeg => convert::decode_mjpeg(data, w, h, &mut image),
        };
        converted.map_err(bad)?;
        if monotonic {
            self.last_ts = Some(b.timestamp_ns);
        }
        self.timestamps = Some(if monotonic {
            Timestamps::Driver
        } else {
            Timestamps::Dequeue
        });
        Ok(SlowFrame::image(t_capture, image, (h, w)))
    }
}

/// A V4L2 node with its mapped buffers.
struct Node {
    fd: OwnedFd,
    maps: Vec<(*mut libc::c_void, usize)>,
    streaming: bool,
}

// SAFETY: the mappings are owned by the node alone and only read through `&self`; moving
// the node to another thread moves that ownership.
unsafe impl Send for Node {}

impl Node {
    fn raw(&self) -> i32 {
        self.fd.as_raw_fd()
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        if self.streaming {
            let mut t = sys::BUF_TYPE_VIDEO_CAPTURE as libc::c_int;
            // SAFETY: STREAMOFF takes a pointer to the buffer type.
            let _ = unsafe { sys::ioctl(self.raw(), sys::VIDIOC_STREAMOFF, &mut t) };
        }
        for &(ptr, len) in &self.maps {
            // SAFETY: each (ptr, len) is a live mapping made by `mmap` in `open`.
            unsafe { libc::munmap(ptr, len) };
        }
    }
}

impl Device for Node {
    fn wait(&mut self, timeout: Duration) -> io::Result<Wait> {
        let mut p = libc::pollfd {
            fd: self.raw(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_nanos().div_ceil(1_000_000).min(i32::MAX as u128) as i32;
        // SAFETY: one valid pollfd.
        let r = unsafe { libc::poll(&mut p, 1, ms) };
        if r < 0 {
            return Err(io::Error::last_os_error());
        }
        if r == 0 {
            return Ok(Wait::TimedOut);
        }
        if p.revents & libc::POLLIN != 0 {
            Ok(Wait::Ready)
        } else if p.revents & (libc::POLLERR | libc::POLLHUP | libc::POLLNVAL) != 0 {
            Ok(Wait::Failed)
        } else {
            Ok(Wait::Ready)
        }
    }

    fn dequeue(&mut self) -> io::Result<Option<Dequeued>> {
        let mut b: sys::Buffer = sys::zeroed();
        b.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        b.memory = sys::MEMORY_MMAP;
        // SAFETY: a v4l2_buffer for VIDIOC_DQBUF. Not retried here: EINTR goes to the loop.
        let r = unsafe { libc::ioctl(self.raw(), sys::VIDIOC_DQBUF as _, &mut b) };
        if r == -1 {
            let e = io::Error::last_os_error();
            return match e.raw_os_error() {
                Some(libc::EAGAIN) => Ok(None),
                _ => Err(e),
            };
        }
        Ok(Some(Dequeued {
            index: b.index,
            bytesused: b.bytesused,
            flags: b.flags,
            sequence: b.sequence,
            timestamp_ns: sys::timeval_ns(&b.timestamp),
        }))
    }

    fn requeue(&mut self, index: u32) -> io::Result<()> {
        let mut b: sys::Buffer = sys::zeroed();
        b.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        b.memory = sys::MEMORY_MMAP;
        b.index = index;
        // SAFETY: a v4l2_buffer for VIDIOC_QBUF.
        unsafe { sys::ioctl(self.raw(), sys::VIDIOC_QBUF, &mut b) }
    }

    fn data(&self, index: u32, len: usize) -> &[u8] {
        match self.maps.get(index as usize) {
            // SAFETY: the mapping is live for `&self` and `len` is clamped to its size.
            Some(&(ptr, size)) => unsafe {
                std::slice::from_raw_parts(ptr as *const u8, len.min(size))
            },
            None => &[],
        }
    }

    fn monotonic_ns(&self) -> u64 {
        sys::monotonic_ns()
    }
}

fn c_string(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

/// The formats and sizes a node offers for video capture.
fn enumerate(fd: i32, device: &str) -> Result<Vec<Offered>> {
    let mut out = Vec::new();
    for index in 0.. {
        let mut d: sys::FmtDesc = sys::zeroed();
        d.index = index;
        d.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        // SAFETY: a v4l2_fmtdesc for VIDIOC_ENUM_FMT.
        match unsafe { sys::ioctl(fd, sys::VIDIOC_ENUM_FMT, &mut d) } {
            Ok(()) => {}
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => break,
            Err(e) => return Err(os_error(device, "VIDIOC_ENUM_FMT", e)),
        }
        let mut discrete = Vec::new();
        let mut sizes = FrameSizes::Unknown;
        for i in 0.. {
            let mut s: sys::FrmSizeEnum = sys::zeroed();
            s.index = i;
            s.pixel_format = d.pixelformat;
            // SAFETY: a v4l2_frmsizeenum for VIDIOC_ENUM_FRAMESIZES.
            if unsafe { sys::ioctl(fd, sys::VIDIOC_ENUM_FRAMESIZES, &mut s) }.is_err() {
                // EINVAL ends the list; a driver without the ioctl leaves sizes unknown.
                break;
            }
            match s.type_ {
                sys::FRMSIZE_TYPE_DISCRETE => {
                    // SAFETY: the driver filled the discrete member.
                    let d = unsafe { s.u.discrete };
                    discrete.push((d.width, d.height));
                    sizes = FrameSizes::Discrete(discrete.clone());
                }
                sys::FRMSIZE_TYPE_CONTINUOUS | sys::FRMSIZE_TYPE_STEPWISE => {
                    // SAFETY: the driver filled the stepwise member.
                    let r = unsafe { s.u.stepwise };
                    let cont = s.type_ == sys::FRMSIZE_TYPE_CONTINUOUS;
                    sizes = FrameSizes::Range {
                        min: (r.min_width, r.min_height),
                        max: (r.max_width, r.max_height),
                        step: if cont {
                            (1, 1)
                        } else {
                            (r.step_width.max(1), r.step_height.max(1))
                        },
                    };
                    break;
                }
                _ => break,
            }
        }
        out.push(Offered {
            fourcc: d.pixelformat,
            sizes,
        });
    }
    Ok(out)
}

/// Open, check, negotiate, map and start streaming (see the module docs).
fn open_node(cfg: &V4l2Config) -> Result<(Node, Negotiated, String, Timestamps)> {
    let device = cfg.device.display().to_string();
    let path = std::ffi::CString::new(cfg.device.as_os_str().as_encoded_bytes()).map_err(|_| {
        Error::CameraUnsupported {
            device: device.clone(),
            reason: "the path holds a NUL byte".into(),
        }
    })?;
    // SAFETY: a NUL-terminated path.
    let fd = unsafe {
        libc::open(
            path.as_ptr(),
            libc::O_RDWR | libc::O_NONBLOCK | libc::O_CLOEXEC,
        )
    };
    if fd < 0 {
        return Err(os_error(&device, "open", io::Error::last_os_error()));
    }
    // SAFETY: `fd` was just opened and is owned here.
    let mut node = Node {
        fd: unsafe { OwnedFd::from_raw_fd(fd) },
        maps: Vec::new(),
        streaming: false,
    };
    let mut cap: sys::Capability = sys::zeroed();
    // SAFETY: a v4l2_capability for VIDIOC_QUERYCAP.
    unsafe { sys::ioctl(fd, sys::VIDIOC_QUERYCAP, &mut cap) }.map_err(|e| {
        if e.raw_os_error() == Some(libc::ENOTTY) {
            Error::CameraUnsupported {
                device: device.clone(),
                reason: "not a V4L2 device".into(),
            }
        } else {
            os_error(&device, "VIDIOC_QUERYCAP", e)
        }
    })?;
    let caps = if cap.capabilities & sys::CAP_DEVICE_CAPS != 0 {
        cap.device_caps
    } else {
        cap.capabilities
    };
    let card = format!("{} ({})", c_string(&cap.card), c_string(&cap.driver));
    let need = sys::CAP_VIDEO_CAPTURE | sys::CAP_STREAMING;
    if caps & need != need {
        return Err(Error::CameraUnsupported {
            device,
            reason: format!(
                "{card} is not a streaming video capture node (capabilities 0x{caps:08x}; \
                 USB cameras also create metadata nodes: try the neighbouring /dev/videoN)"
            ),
        });
    }
    let offered = enumerate(fd, &device)?;
    let choice = choose(&device, &offered, &cfg.request)?;
    let mut f: sys::Format = sys::zeroed();
    f.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
    f.fmt.pix = sys::PixFormat {
        width: choice.size.0,
        height: choice.size.1,
        pixelformat: choice.format.fourcc(),
        field: sys::FIELD_NONE,
        ..Default::default()
    };
    // SAFETY: a v4l2_format for VIDIOC_S_FMT.
    unsafe { sys::ioctl(fd, sys::VIDIOC_S_FMT, &mut f) }
        .map_err(|e| os_error(&device, "VIDIOC_S_FMT", e))?;
    // SAFETY: the driver filled the `pix` member of a capture format.
    let pix = unsafe { f.fmt.pix };
    let negotiated = accept(&device, &choice, &pix)?;
    if pix.field != sys::FIELD_NONE && pix.field != sys::FIELD_ANY {
        return Err(Error::CameraFormat {
            device,
            asked: format!("{negotiated} progressive"),
            offered: format!("interlaced frames (field order {})", pix.field),
        });
    }

    let mut rb = sys::RequestBuffers {
        count: cfg.buffers.max(2),
        type_: sys::BUF_TYPE_VIDEO_CAPTURE,
        memory: sys::MEMORY_MMAP,
        ..Default::default()
    };
    // SAFETY: a v4l2_requestbuffers for VIDIOC_REQBUFS.
    unsafe { sys::ioctl(fd, sys::VIDIOC_REQBUFS, &mut rb) }
        .map_err(|e| os_error(&device, "VIDIOC_REQBUFS", e))?;
    if rb.count < 2 {
        return Err(Error::CameraUnsupported {
            device,
            reason: format!("the driver granted {} mmap buffers, 2 needed", rb.count),
        });
    }
    let mut stamps = Timestamps::Driver;
    for index in 0..rb.count {
        let mut b: sys::Buffer = sys::zeroed();
        b.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        b.memory = sys::MEMORY_MMAP;
        b.index = index;
        // SAFETY: a v4l2_buffer for VIDIOC_QUERYBUF.
        unsafe { sys::ioctl(fd, sys::VIDIOC_QUERYBUF, &mut b) }
            .map_err(|e| os_error(&device, "VIDIOC_QUERYBUF", e))?;
        if b.flags & sys::BUF_FLAG_TIMESTAMP_MASK != sys::BUF_FLAG_TIMESTAMP_MONOTONIC {
            stamps = Timestamps::Dequeue;
        }
        // SAFETY: the offset member is the one set for MMAP buffers.
        let offset = unsafe { b.m.offset };
        // SAFETY: maps `length` bytes of the driver's buffer at the offset it gave.
        let ptr = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                b.length as usize,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                fd,
                offset as libc::off_t,
            )
        };
        if ptr == libc::MAP_FAILED {
            return Err(os_error(&device, "mmap", io::Error::last_os_error()));
        }
        node.maps.push((ptr, b.length as usize));
        node.requeue(index)
            .map_err(|e| os_error(&device, "VIDIOC_QBUF", e))?;
    }
    let mut t = sys::BUF_TYPE_VIDEO_CAPTURE as libc::c_int;
    // SAFETY: STREAMON takes a pointer to the buffer type.
    unsafe { sys::ioctl(fd, sys::VIDIOC_STREAMON, &mut t) }
        .map_err(|e| os_error(&device, "VIDIOC_STREAMON", e))?;
    node.streaming = true;
    Ok((node, negotiated, card, stamps))
}

/// A live V4L2 camera (see the module docs).
pub struct V4l2Camera {
    capture: Capture<Node>,
    card: String,
}

impl fmt::Display for Timestamps {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Timestamps::Driver => "driver capture timestamps",
            Timestamps::Dequeue => {
                "dequeue-time timestamps (the driver gives no monotonic capture time)"
            }
        })
    }
}

impl fmt::Debug for V4l2Camera {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("V4l2Camera")
            .field("device", &self.capture.device)
            .field("card", &self.card)
            .field("format", &self.capture.format)
            .field("counters", &self.capture.counters)
            .finish_non_exhaustive()
    }
}

impl V4l2Camera {
    /// Open and start the camera; frames are stamped on `clock`.
    pub fn open(cfg: &V4l2Config, clock: Arc<dyn Clock>) -> Result<Self> {
        let (node, format, card, stamps) = open_node(cfg)?;
        let device = cfg.device.display().to_string();
        let mut capture = Capture::new(node, device, format, cfg.timeout, clock);
        capture.timestamps = Some(stamps);
        Ok(Self { capture, card })
    }

    /// The device path.
    pub fn device(&self) -> &Path {
        Path::new(&self.capture.device)
    }

    /// The format the driver settled on.
    pub fn format(&self) -> Negotiated {
        self.capture.format
    }

    /// The device's name and driver, as `VIDIOC_QUERYCAP` gives them.
    pub fn card(&self) -> &str {
        &self.card
    }

    /// Where the last frame's capture time came from (before the first frame: what the
    /// driver announced for its buffers at `VIDIOC_QUERYBUF`).
    pub fn timestamps(&self) -> Timestamps {
        self.capture.timestamps.unwrap_or(Timestamps::Dequeue)
    }

    /// The camera's counters.
    pub fn counters(&self) -> &CameraCounters {
        &self.capture.counters
    }

    /// The delivered-frames counter (shared; keep it before handing the camera to a run).
    pub fn frames(&self) -> Arc<AtomicU64> {
        self.capture.counters.delivered.clone()
    }

    /// Capture the newest frame, blocking up to the configured timeout.
    pub fn capture_frame(&mut self) -> Result<SlowFrame> {
        self.capture.next_frame()
    }
}

#[async_trait::async_trait]
impl SlowSource for V4l2Camera {
    async fn capture(&mut self) -> pir2_runtime::Result<SlowFrame> {
        self.capture_frame()
            .map_err(|e| pir2_runtime::Error::io("V4L2", e))
    }
}

#[cfg(test)]
mod tests;
