//! The slice of the kernel's V4L2 user API (`linux/videodev2.h`) the camera uses: `repr(C)`
//! mirrors of its structs, its constants and its ioctl request numbers, and thin wrappers
//! around `ioctl`, `poll`, `mmap` and `clock_gettime`.
//!
//! The layouts are checked in the tests: against numbers verified once on x86_64 with a C
//! program compiled against the kernel header (always), and against that header itself when
//! a C compiler and the header are present (`v4l2_layout_matches_the_kernel_header`).

use std::io;
use std::os::fd::RawFd;

/// `V4L2_BUF_TYPE_VIDEO_CAPTURE`.
pub const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
/// `V4L2_MEMORY_MMAP`.
pub const MEMORY_MMAP: u32 = 1;
/// `V4L2_FIELD_ANY` (let the driver choose) and `V4L2_FIELD_NONE` (progressive).
pub const FIELD_ANY: u32 = 0;
/// `V4L2_FIELD_NONE`.
pub const FIELD_NONE: u32 = 1;

/// `V4L2_CAP_VIDEO_CAPTURE`.
pub const CAP_VIDEO_CAPTURE: u32 = 0x0000_0001;
/// `V4L2_CAP_STREAMING`.
pub const CAP_STREAMING: u32 = 0x0400_0000;
/// `V4L2_CAP_DEVICE_CAPS`: `device_caps` is valid (describes this node, not the whole device).
pub const CAP_DEVICE_CAPS: u32 = 0x8000_0000;

/// `V4L2_FRMSIZE_TYPE_DISCRETE`, `_CONTINUOUS`, `_STEPWISE`.
pub const FRMSIZE_TYPE_DISCRETE: u32 = 1;
/// See [`FRMSIZE_TYPE_DISCRETE`].
pub const FRMSIZE_TYPE_CONTINUOUS: u32 = 2;
/// See [`FRMSIZE_TYPE_DISCRETE`].
pub const FRMSIZE_TYPE_STEPWISE: u32 = 3;

/// `V4L2_BUF_FLAG_ERROR`: the buffer was filled but its data may be corrupt.
pub const BUF_FLAG_ERROR: u32 = 0x0000_0040;
/// `V4L2_BUF_FLAG_TIMESTAMP_MASK`.
pub const BUF_FLAG_TIMESTAMP_MASK: u32 = 0x0000_e000;
/// `V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`: `timestamp` is on `CLOCK_MONOTONIC`.
pub const BUF_FLAG_TIMESTAMP_MONOTONIC: u32 = 0x0000_2000;
/// `V4L2_BUF_FLAG_TSTAMP_SRC_MASK`.
pub const BUF_FLAG_TSTAMP_SRC_MASK: u32 = 0x0007_0000;
/// `V4L2_BUF_FLAG_TSTAMP_SRC_SOE`: taken at the start of exposure (else: end of frame).
pub const BUF_FLAG_TSTAMP_SRC_SOE: u32 = 0x0001_0000;

/// A V4L2 FourCC code from its four characters.
pub const fn fourcc(c: &[u8; 4]) -> u32 {
    (c[0] as u32) | ((c[1] as u32) << 8) | ((c[2] as u32) << 16) | ((c[3] as u32) << 24)
}

/// `V4L2_PIX_FMT_YUYV`: packed YUV 4:2:2, `Y0 U Y1 V` per two pixels.
pub const PIX_FMT_YUYV: u32 = fourcc(b"YUYV");
/// `V4L2_PIX_FMT_MJPEG`: one JPEG image per frame (Huffman tables possibly omitted).
pub const PIX_FMT_MJPEG: u32 = fourcc(b"MJPG");
/// `V4L2_PIX_FMT_RGB24`: packed `R G B`.
pub const PIX_FMT_RGB24: u32 = fourcc(b"RGB3");

/// `struct v4l2_capability`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct Capability {
    /// Driver name (NUL-terminated).
    pub driver: [u8; 16],
    /// Device name.
    pub card: [u8; 32],
    /// Bus location.
    pub bus_info: [u8; 32],
    /// Kernel version of the driver.
    pub version: u32,
    /// Capabilities of the whole physical device.
    pub capabilities: u32,
    /// Capabilities of this node (valid with [`CAP_DEVICE_CAPS`]).
    pub device_caps: u32,
    /// Reserved.
    pub reserved: [u32; 3],
}

/// `struct v4l2_fmtdesc`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct FmtDesc {
    /// Index to enumerate (set by us).
    pub index: u32,
    /// Buffer type (set by us).
    pub type_: u32,
    /// `V4L2_FMT_FLAG_*`.
    pub flags: u32,
    /// Human-readable name.
    pub description: [u8; 32],
    /// FourCC.
    pub pixelformat: u32,
    /// Media bus code (unused here).
    pub mbus_code: u32,
    /// Reserved.
    pub reserved: [u32; 3],
}

/// `struct v4l2_frmsize_discrete`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct FrmSizeDiscrete {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

/// `struct v4l2_frmsize_stepwise`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct FrmSizeStepwise {
    /// Minimum width.
    pub min_width: u32,
    /// Maximum width.
    pub max_width: u32,
    /// Width step.
    pub step_width: u32,
    /// Minimum height.
    pub min_height: u32,
    /// Maximum height.
    pub max_height: u32,
    /// Height step.
    pub step_height: u32,
}

/// The union of `struct v4l2_frmsizeenum`.
#[repr(C)]
#[derive(Clone, Copy)]
pub union FrmSizeUnion {
    /// For [`FRMSIZE_TYPE_DISCRETE`].
    pub discrete: FrmSizeDiscrete,
    /// For [`FRMSIZE_TYPE_CONTINUOUS`] and [`FRMSIZE_TYPE_STEPWISE`].
    pub stepwise: FrmSizeStepwise,
}

/// `struct v4l2_frmsizeenum`.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct FrmSizeEnum {
    /// Index to enumerate (set by us).
    pub index: u32,
    /// FourCC whose sizes are enumerated (set by us).
    pub pixel_format: u32,
    /// `FRMSIZE_TYPE_*`.
    pub type_: u32,
    /// The size or range.
    pub u: FrmSizeUnion,
    /// Reserved.
    pub reserved: [u32; 2],
}

/// `struct v4l2_pix_format`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct PixFormat {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// FourCC.
    pub pixelformat: u32,
    /// `V4L2_FIELD_*`.
    pub field: u32,
    /// Bytes per row (0 for compressed formats).
    pub bytesperline: u32,
    /// Bytes per frame buffer.
    pub sizeimage: u32,
    /// Colour space.
    pub colorspace: u32,
    /// Private / `V4L2_PIX_FMT_PRIV_MAGIC`.
    pub priv_: u32,
    /// `V4L2_PIX_FMT_FLAG_*`.
    pub flags: u32,
    /// Y'CbCr encoding.
    pub ycbcr_enc: u32,
    /// Quantization (full or limited range).
    pub quantization: u32,
    /// Transfer function.
    pub xfer_func: u32,
}

/// The union of `struct v4l2_format` (200 bytes, pointer-aligned: some members hold pointers).
#[repr(C)]
#[derive(Clone, Copy)]
pub union FormatUnion {
    /// For single-planar capture.
    pub pix: PixFormat,
    /// The union's full size.
    pub raw_data: [u8; 200],
    /// The union's alignment (`struct v4l2_window` holds pointers).
    pub align: [usize; 0],
}

/// `struct v4l2_format`.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct Format {
    /// Buffer type.
    pub type_: u32,
    /// The format.
    pub fmt: FormatUnion,
}

/// `struct v4l2_requestbuffers`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct RequestBuffers {
    /// Buffers asked (in) / granted (out).
    pub count: u32,
    /// Buffer type.
    pub type_: u32,
    /// Memory kind.
    pub memory: u32,
    /// `V4L2_BUF_CAP_*` (out).
    pub capabilities: u32,
    /// `V4L2_MEMORY_FLAG_*`.
    pub flags: u8,
    /// Reserved.
    pub reserved: [u8; 3],
}

/// `struct v4l2_timecode`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct Timecode {
    /// Frame rate type.
    pub type_: u32,
    /// Flags.
    pub flags: u32,
    /// Frames.
    pub frames: u8,
    /// Seconds.
    pub seconds: u8,
    /// Minutes.
    pub minutes: u8,
    /// Hours.
    pub hours: u8,
    /// User bits.
    pub userbits: [u8; 4],
}

/// The `m` union of `struct v4l2_buffer`.
#[repr(C)]
#[derive(Clone, Copy)]
pub union BufferM {
    /// With [`MEMORY_MMAP`]: the offset to pass to `mmap`.
    pub offset: u32,
    /// With `V4L2_MEMORY_USERPTR`.
    pub userptr: libc::c_ulong,
    /// With `V4L2_MEMORY_DMABUF`.
    pub fd: i32,
}

/// `struct v4l2_buffer`.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct Buffer {
    /// Buffer index.
    pub index: u32,
    /// Buffer type.
    pub type_: u32,
    /// Bytes of data in the buffer.
    pub bytesused: u32,
    /// `V4L2_BUF_FLAG_*`.
    pub flags: u32,
    /// Field order.
    pub field: u32,
    /// Capture time (clock given by the timestamp flags).
    pub timestamp: libc::timeval,
    /// Timecode.
    pub timecode: Timecode,
    /// Frame counter set by the driver.
    pub sequence: u32,
    /// Memory kind.
    pub memory: u32,
    /// Where the data lives.
    pub m: BufferM,
    /// Buffer size in bytes.
    pub length: u32,
    /// Reserved.
    pub reserved2: u32,
    /// `request_fd` / reserved.
    pub request_fd: i32,
}

/// Unions print as their name only (which member is valid depends on the other fields).
macro_rules! opaque_debug {
    ($($t:ty),*) => {$(
        impl std::fmt::Debug for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(stringify!($t))
            }
        }
    )*};
}
opaque_debug!(FrmSizeUnion, FormatUnion, BufferM);

impl std::fmt::Debug for FrmSizeEnum {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrmSizeEnum")
            .field("index", &self.index)
            .field("pixel_format", &self.pixel_format)
            .field("type_", &self.type_)
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Format")
            .field("type_", &self.type_)
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for Buffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Buffer")
            .field("index", &self.index)
            .field("bytesused", &self.bytesused)
            .field("flags", &self.flags)
            .field("sequence", &self.sequence)
            .finish_non_exhaustive()
    }
}

/// The structs of this module for which all-zero bytes are a valid value.
///
/// # Safety
/// Only for `repr(C)` types whose fields are integers, or arrays, structs or unions of
/// integers (no references, no pointers that are dereferenced, no enums).
pub(crate) unsafe trait Zeroable: Copy {}
// SAFETY: every one of these is integers (and arrays/unions/structs of integers) only.
unsafe impl Zeroable for Capability {}
// SAFETY: as above.
unsafe impl Zeroable for FmtDesc {}
// SAFETY: as above.
unsafe impl Zeroable for FrmSizeEnum {}
// SAFETY: as above (the union's `align` member is a zero-length array).
unsafe impl Zeroable for Format {}
// SAFETY: as above (`libc::timeval` is two integers).
unsafe impl Zeroable for Buffer {}

/// An all-zero value of a V4L2 struct (the state the kernel API expects before the fields
/// a call reads are set).
pub(crate) fn zeroed<T: Zeroable>() -> T {
    // SAFETY: `Zeroable` types accept all-zero bytes.
    unsafe { std::mem::zeroed() }
}

const IOC_WRITE: u32 = 1;
const IOC_READ: u32 = 2;

/// `_IOC(dir, 'V', nr, size)`.
const fn ioc(dir: u32, nr: u32, size: usize) -> u32 {
    (dir << 30) | ((size as u32) << 16) | ((b'V' as u32) << 8) | nr
}

/// `VIDIOC_QUERYCAP`.
pub const VIDIOC_QUERYCAP: u32 = ioc(IOC_READ, 0, std::mem::size_of::<Capability>());
/// `VIDIOC_ENUM_FMT`.
pub const VIDIOC_ENUM_FMT: u32 = ioc(IOC_READ | IOC_WRITE, 2, std::mem::size_of::<FmtDesc>());
/// `VIDIOC_G_FMT`.
pub const VIDIOC_G_FMT: u32 = ioc(IOC_READ | IOC_WRITE, 4, std::mem::size_of::<Format>());
/// `VIDIOC_S_FMT`.
pub const VIDIOC_S_FMT: u32 = ioc(IOC_READ | IOC_WRITE, 5, std::mem::size_of::<Format>());
/// `VIDIOC_REQBUFS`.
pub const VIDIOC_REQBUFS: u32 = ioc(
    IOC_READ | IOC_WRITE,
    8,
    std::mem::size_of::<RequestBuffers>(),
);
/// `VIDIOC_QUERYBUF`.
pub const VIDIOC_QUERYBUF: u32 = ioc(IOC_READ | IOC_WRITE, 9, std::mem::size_of::<Buffer>());
/// `VIDIOC_QBUF`.
pub const VIDIOC_QBUF: u32 = ioc(IOC_READ | IOC_WRITE, 15, std::mem::size_of::<Buffer>());
/// `VIDIOC_DQBUF`.
pub const VIDIOC_DQBUF: u32 = ioc(IOC_READ | IOC_WRITE, 17, std::mem::size_of::<Buffer>());
/// `VIDIOC_STREAMON`.
pub const VIDIOC_STREAMON: u32 = ioc(IOC_WRITE, 18, std::mem::size_of::<libc::c_int>());
/// `VIDIOC_STREAMOFF`.
pub const VIDIOC_STREAMOFF: u32 = ioc(IOC_WRITE, 19, std::mem::size_of::<libc::c_int>());
/// `VIDIOC_ENUM_FRAMESIZES`.
pub const VIDIOC_ENUM_FRAMESIZES: u32 =
    ioc(IOC_READ | IOC_WRITE, 74, std::mem::size_of::<FrmSizeEnum>());

/// `ioctl(fd, request, arg)`, retried on `EINTR`.
///
/// # Safety
/// `arg` must point to the struct `request` expects (its size is encoded in `request`).
pub unsafe fn ioctl<T>(fd: RawFd, request: u32, arg: *mut T) -> io::Result<()> {
    loop {
        // SAFETY: the caller guarantees `arg` matches `request`.
        let r = unsafe { libc::ioctl(fd, request as _, arg) };
        if r != -1 {
            return Ok(());
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// `CLOCK_MONOTONIC` now, in nanoseconds.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// A buffer's `timestamp` in nanoseconds (negative fields, which no driver sets, give 0).
pub fn timeval_ns(tv: &libc::timeval) -> u64 {
    let s = u64::try_from(tv.tv_sec).unwrap_or(0);
    let us = u64::try_from(tv.tv_usec).unwrap_or(0);
    s.saturating_mul(1_000_000_000)
        .saturating_add(us.saturating_mul(1000))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{offset_of, size_of};

    /// The x86_64 numbers, printed by a C program compiled against `linux/videodev2.h` of
    /// Debian's `linux-libc-dev` 6.1 (the program is the one the next test compiles).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn v4l2_layout_matches_the_verified_x86_64_numbers() {
        assert_eq!(size_of::<Capability>(), 104);
        assert_eq!(size_of::<FmtDesc>(), 64);
        assert_eq!(size_of::<FrmSizeEnum>(), 44);
        assert_eq!(size_of::<Format>(), 208);
        assert_eq!(size_of::<PixFormat>(), 48);
        assert_eq!(size_of::<RequestBuffers>(), 20);
        assert_eq!(size_of::<Buffer>(), 88);
        assert_eq!(size_of::<Timecode>(), 16);
        assert_eq!(offset_of!(Capability, capabilities), 84);
        assert_eq!(offset_of!(Capability, device_caps), 88);
        assert_eq!(offset_of!(FmtDesc, flags), 8);
        assert_eq!(offset_of!(FmtDesc, description), 12);
        assert_eq!(offset_of!(FmtDesc, pixelformat), 44);
        assert_eq!(offset_of!(FrmSizeEnum, type_), 8);
        assert_eq!(offset_of!(FrmSizeEnum, u), 12);
        assert_eq!(offset_of!(Format, fmt), 8);
        assert_eq!(offset_of!(PixFormat, bytesperline), 16);
        assert_eq!(offset_of!(PixFormat, sizeimage), 20);
        assert_eq!(offset_of!(Buffer, flags), 12);
        assert_eq!(offset_of!(Buffer, timestamp), 24);
        assert_eq!(offset_of!(Buffer, timecode), 40);
        assert_eq!(offset_of!(Buffer, sequence), 56);
        assert_eq!(offset_of!(Buffer, memory), 60);
        assert_eq!(offset_of!(Buffer, m), 64);
        assert_eq!(offset_of!(Buffer, length), 72);
        assert_eq!(offset_of!(Buffer, request_fd), 80);
        let requests = [
            (VIDIOC_QUERYCAP, 0x8068_5600),
            (VIDIOC_ENUM_FMT, 0xc040_5602),
            (VIDIOC_G_FMT, 0xc0d0_5604),
            (VIDIOC_S_FMT, 0xc0d0_5605),
            (VIDIOC_REQBUFS, 0xc014_5608),
            (VIDIOC_QUERYBUF, 0xc058_5609),
            (VIDIOC_QBUF, 0xc058_560f),
            (VIDIOC_DQBUF, 0xc058_5611),
            (VIDIOC_STREAMON, 0x4004_5612),
            (VIDIOC_STREAMOFF, 0x4004_5613),
            (VIDIOC_ENUM_FRAMESIZES, 0xc02c_564a),
        ];
        for (ours, kernel) in requests {
            assert_eq!(ours, kernel, "0x{ours:x} != 0x{kernel:x}");
        }
        assert_eq!(PIX_FMT_YUYV, 0x5659_5559);
        assert_eq!(PIX_FMT_MJPEG, 0x4750_4a4d);
        assert_eq!(PIX_FMT_RGB24, 0x3342_4752);
    }

    /// The same checks against the kernel header itself, on whatever machine runs the test:
    /// compiles a small C program with `cc` and compares every size, offset and request
    /// number it prints with ours. Skipped (with a note on stderr) without `cc` or the
    /// header (Debian: `linux-libc-dev`).
    #[test]
    fn v4l2_layout_matches_the_kernel_header() {
        let dir = std::env::temp_dir().join(format!("pir2-v4l2-layout-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let src = dir.join("layout.c");
        std::fs::write(&src, C_PROGRAM).unwrap();
        let exe = dir.join("layout");
        let cc = std::process::Command::new("cc")
            .arg(&src)
            .arg("-o")
            .arg(&exe)
            .output();
        match cc {
            Err(e) => {
                eprintln!("skipped: cannot run cc: {e}");
                std::fs::remove_dir_all(&dir).ok();
                return;
            }
            Ok(o) if !o.status.success() => {
                let err = String::from_utf8_lossy(&o.stderr);
                std::fs::remove_dir_all(&dir).ok();
                assert!(err.contains("videodev2.h"), "cc failed: {err}");
                eprintln!("skipped: no linux/videodev2.h (Debian: linux-libc-dev): {err}");
                return;
            }
            Ok(_) => {}
        }
        let out = std::process::Command::new(&exe).output().unwrap();
        std::fs::remove_dir_all(&dir).ok();
        let text = String::from_utf8(out.stdout).unwrap();
        let ours: Vec<(&str, u64)> = vec![
            ("sizeof v4l2_capability", size_of::<Capability>() as u64),
            ("sizeof v4l2_fmtdesc", size_of::<FmtDesc>() as u64),
            ("sizeof v4l2_frmsizeenum", size_of::<FrmSizeEnum>() as u64),
            ("sizeof v4l2_format", size_of::<Format>() as u64),
            ("sizeof v4l2_pix_format", size_of::<PixFormat>() as u64),
            (
                "sizeof v4l2_requestbuffers",
                size_of::<RequestBuffers>() as u64,
            ),
            ("sizeof v4l2_buffer", size_of::<Buffer>() as u64),
            (
                "offsetof v4l2_capability.device_caps",
                offset_of!(Capability, device_caps) as u64,
            ),
            (
                "offsetof v4l2_fmtdesc.pixelformat",
                offset_of!(FmtDesc, pixelformat) as u64,
            ),
            (
                "offsetof v4l2_frmsizeenum.discrete",
                offset_of!(FrmSizeEnum, u) as u64,
            ),
            ("offsetof v4l2_format.fmt", offset_of!(Format, fmt) as u64),
            (
                "offsetof v4l2_pix_format.sizeimage",
                offset_of!(PixFormat, sizeimage) as u64,
            ),
            (
                "offsetof v4l2_pix_format.quantization",
                offset_of!(PixFormat, quantization) as u64,
            ),
            (
                "offsetof v4l2_buffer.timestamp",
                offset_of!(Buffer, timestamp) as u64,
            ),
            (
                "offsetof v4l2_buffer.sequence",
                offset_of!(Buffer, sequence) as u64,
            ),
            ("offsetof v4l2_buffer.m", offset_of!(Buffer, m) as u64),
            (
                "offsetof v4l2_buffer.length",
                offset_of!(Buffer, length) as u64,
            ),
            (
                "offsetof v4l2_buffer.request_fd",
                offset_of!(Buffer, request_fd) as u64,
            ),
            ("ioctl VIDIOC_QUERYCAP", VIDIOC_QUERYCAP as u64),
            ("ioctl VIDIOC_ENUM_FMT", VIDIOC_ENUM_FMT as u64),
            ("ioctl VIDIOC_G_FMT", VIDIOC_G_FMT as u64),
            ("ioctl VIDIOC_S_FMT", VIDIOC_S_FMT as u64),
            ("ioctl VIDIOC_REQBUFS", VIDIOC_REQBUFS as u64),
            ("ioctl VIDIOC_QUERYBUF", VIDIOC_QUERYBUF as u64),
            ("ioctl VIDIOC_QBUF", VIDIOC_QBUF as u64),
            ("ioctl VIDIOC_DQBUF", VIDIOC_DQBUF as u64),
            ("ioctl VIDIOC_STREAMON", VIDIOC_STREAMON as u64),
            ("ioctl VIDIOC_STREAMOFF", VIDIOC_STREAMOFF as u64),
            (
                "ioctl VIDIOC_ENUM_FRAMESIZES",
                VIDIOC_ENUM_FRAMESIZES as u64,
            ),
            ("const V4L2_PIX_FMT_YUYV", PIX_FMT_YUYV as u64),
            ("const V4L2_PIX_FMT_MJPEG", PIX_FMT_MJPEG as u64),
            ("const V4L2_PIX_FMT_RGB24", PIX_FMT_RGB24 as u64),
            ("const V4L2_CAP_STREAMING", CAP_STREAMING as u64),
            ("const V4L2_BUF_FLAG_ERROR", BUF_FLAG_ERROR as u64),
            (
                "const V4L2_BUF_FLAG_TIMESTAMP_MASK",
                BUF_FLAG_TIMESTAMP_MASK as u64,
            ),
            (
                "const V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC",
                BUF_FLAG_TIMESTAMP_MONOTONIC as u64,
            ),
            (
                "const V4L2_BUF_FLAG_TSTAMP_SRC_SOE",
                BUF_FLAG_TSTAMP_SRC_SOE as u64,
            ),
        ];
        let kernel: std::collections::HashMap<&str, u64> = text
            .lines()
            .filter_map(|l| l.rsplit_once(' '))
            .map(|(k, v)| (k, v.parse().unwrap()))
            .collect();
        assert_eq!(kernel.len(), ours.len(), "{text}");
        for (name, v) in ours {
            assert_eq!(kernel.get(name), Some(&v), "{name}: kernel vs ours\n{text}");
        }
    }

    const C_PROGRAM: &str = r#"
#include <stdio.h>
#include <stddef.h>
#include <linux/videodev2.h>
#define S(t) printf("sizeof %s %zu\n", #t, sizeof(struct t))
#define O(t, f) printf("offsetof %s.%s %zu\n", #t, #f, offsetof(struct t, f))
#define R(r) printf("ioctl %s %lu\n", #r, (unsigned long)(r))
#define C(c) printf("const %s %lu\n", #c, (unsigned long)(c))
int main(void) {
    S(v4l2_capability); S(v4l2_fmtdesc); S(v4l2_frmsizeenum); S(v4l2_format);
    S(v4l2_pix_format); S(v4l2_requestbuffers); S(v4l2_buffer);
    O(v4l2_capability, device_caps); O(v4l2_fmtdesc, pixelformat);
    O(v4l2_frmsizeenum, discrete); O(v4l2_format, fmt); O(v4l2_pix_format, sizeimage);
    O(v4l2_pix_format, quantization);
    O(v4l2_buffer, timestamp); O(v4l2_buffer, sequence); O(v4l2_buffer, m);
    O(v4l2_buffer, length); O(v4l2_buffer, request_fd);
    R(VIDIOC_QUERYCAP); R(VIDIOC_ENUM_FMT); R(VIDIOC_G_FMT); R(VIDIOC_S_FMT);
    R(VIDIOC_REQBUFS); R(VIDIOC_QUERYBUF); R(VIDIOC_QBUF); R(VIDIOC_DQBUF);
    R(VIDIOC_STREAMON); R(VIDIOC_STREAMOFF); R(VIDIOC_ENUM_FRAMESIZES);
    C(V4L2_PIX_FMT_YUYV); C(V4L2_PIX_FMT_MJPEG); C(V4L2_PIX_FMT_RGB24);
    C(V4L2_CAP_STREAMING); C(V4L2_BUF_FLAG_ERROR); C(V4L2_BUF_FLAG_TIMESTAMP_MASK);
    C(V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC); C(V4L2_BUF_FLAG_TSTAMP_SRC_SOE);
    return 0;
}
"#;
}
