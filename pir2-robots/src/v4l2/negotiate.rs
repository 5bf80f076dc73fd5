//! Format negotiation as a pure function of what the device offers and what was asked.
//!
//! The camera enumerates the device's pixel formats (`VIDIOC_ENUM_FMT`) and, per format, its
//! frame sizes (`VIDIOC_ENUM_FRAMESIZES`: a list, a stepped range, or nothing when the driver
//! does not enumerate sizes) into [`Offered`] values; [`choose`] picks one format and size
//! from them; the camera asks the driver for it (`VIDIOC_S_FMT`) and [`accept`] checks what
//! the driver answered, which is what the camera then uses.
//!
//! Rules of [`choose`]:
//! - Only [`PixelFormat`]s this crate converts to RGB are candidates (a requested format
//!   must be one of them and be offered).
//! - An explicit size must be offered exactly (in a list, or on a range's steps) by a
//!   candidate; without one, each candidate's size nearest to [`DEFAULT_SIZE`] is taken
//!   (nearest by `|Δw| + |Δh|`, ties to the larger) and the nearest over candidates wins.
//! - Between formats offering the chosen size equally well, the order of
//!   [`PixelFormat::PREFERENCE`] decides: uncompressed formats first (no decoding cost, no
//!   compression artefacts); UVC webcams typically offer their larger sizes in MJPEG only,
//!   where MJPEG is then chosen.
//! - Nothing usable is one [`Error::CameraFormat`] naming the device, what was asked and
//!   everything the device offered (unsupported formats included, by name).

use std::fmt;

use super::sys;
use crate::error::{Error, Result};

/// The size looked for when none is asked: the 640×480 of common robot cameras.
pub const DEFAULT_SIZE: (u32, u32) = (640, 480);

/// The pixel formats the camera converts to HWC `u8` RGB.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PixelFormat {
    /// Packed RGB, 3 bytes per pixel (`RGB3`): copied row by row.
    Rgb24,
    /// Packed YUV 4:2:2 (`YUYV`): converted with BT.601 limited-range coefficients.
    Yuyv,
    /// Motion JPEG (`MJPG`): one JPEG per frame, decoded (missing Huffman tables, as UVC
    /// cameras send them, are the JPEG standard's defaults).
    Mjpeg,
}

impl PixelFormat {
    /// The order in which equally good formats are preferred.
    pub const PREFERENCE: [PixelFormat; 3] =
        [PixelFormat::Rgb24, PixelFormat::Yuyv, PixelFormat::Mjpeg];

    /// The V4L2 FourCC.
    pub fn fourcc(self) -> u32 {
        match self {
            PixelFormat::Rgb24 => sys::PIX_FMT_RGB24,
            PixelFormat::Yuyv => sys::PIX_FMT_YUYV,
            PixelFormat::Mjpeg => sys::PIX_FMT_MJPEG,
        }
    }

    /// The format of a FourCC, if supported.
    pub fn from_fourcc(code: u32) -> Option<Self> {
        Self::PREFERENCE.into_iter().find(|f| f.fourcc() == code)
    }

    /// Bytes per pixel of an uncompressed format (`None` for MJPEG).
    pub fn bytes_per_pixel(self) -> Option<u32> {
        match self {
            PixelFormat::Rgb24 => Some(3),
            PixelFormat::Yuyv => Some(2),
            PixelFormat::Mjpeg => None,
        }
    }

    fn rank(self) -> usize {
        Self::PREFERENCE
            .iter()
            .position(|&f| f == self)
            .unwrap_or(usize::MAX)
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            PixelFormat::Rgb24 => "RGB24",
            PixelFormat::Yuyv => "YUYV",
            PixelFormat::Mjpeg => "MJPEG",
        })
    }
}

impl std::str::FromStr for PixelFormat {
    type Err = Error;
    /// `mjpeg` (or `mjpg`), `yuyv`, `rgb24`; any case.
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "mjpeg" | "mjpg" => Ok(PixelFormat::Mjpeg),
            "yuyv" => Ok(PixelFormat::Yuyv),
            "rgb24" => Ok(PixelFormat::Rgb24),
            _ => Err(Error::Config(format!(
                "camera pixel format {s:?}: expected mjpeg, yuyv or rgb24"
            ))),
        }
    }
}

/// A FourCC as text (`MJPG`, `H264`, …; non-printable bytes as `?`).
pub fn fourcc_name(code: u32) -> String {
    code.to_le_bytes()
        .iter()
        .map(|&b| {
            if b.is_ascii_graphic() || b == b' ' {
                b as char
            } else {
                '?'
            }
        })
        .collect::<String>()
        .trim_end()
        .to_string()
}

/// Parse `WxH` (e.g. `640x480`).
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let bad = || {
        Error::Config(format!(
            "camera size {s:?}: expected WIDTHxHEIGHT, e.g. 640x480"
        ))
    };
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok((w, h))
}

/// The frame sizes a device offers for one format.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FrameSizes {
    /// A list of sizes (`V4L2_FRMSIZE_TYPE_DISCRETE`).
    Discrete(Vec<(u32, u32)>),
    /// Every `min + k·step` up to `max` in each dimension (`STEPWISE`; `CONTINUOUS` has
    /// step 1).
    Range {
        /// Smallest width and height.
        min: (u32, u32),
        /// Largest width and height.
        max: (u32, u32),
        /// Width and height steps (≥ 1).
        step: (u32, u32),
    },
    /// The driver does not enumerate sizes: the driver decides at `VIDIOC_S_FMT`.
    Unknown,
}

fn on_steps(v: u32, min: u32, max: u32, step: u32) -> bool {
    v >= min && v <= max && (v - min) % step.max(1) == 0
}

fn snap(v: u32, min: u32, max: u32, step: u32) -> u32 {
    let step = step.max(1);
    let v = v.clamp(min, max);
    let k = ((v - min) as f64 / step as f64).round() as u32;
    let s = min + k * step;
    if s > max {
        s - step
    } else {
        s
    }
}

fn distance(a: (u32, u32), b: (u32, u32)) -> u64 {
    a.0.abs_diff(b.0) as u64 + a.1.abs_diff(b.1) as u64
}

impl FrameSizes {
    /// Whether `size` is offered exactly (always true for [`FrameSizes::Unknown`]).
    pub fn offers(&self, size: (u32, u32)) -> bool {
        match self {
            FrameSizes::Discrete(v) => v.contains(&size),
            FrameSizes::Range { min, max, step } => {
                on_steps(size.0, min.0, max.0, step.0) && on_steps(size.1, min.1, max.1, step.1)
            }
            FrameSizes::Unknown => true,
        }
    }

    /// The offered size nearest to `target` (`|Δw| + |Δh|`, ties to the larger area);
    /// `None` for an empty list. [`FrameSizes::Unknown`] gives `target`.
    pub fn nearest(&self, target: (u32, u32)) -> Option<(u32, u32)> {
        match self {
            FrameSizes::Discrete(v) => v.iter().copied().min_by_key(|&s| {
                (
                    distance(s, target),
                    std::cmp::Reverse(s.0 as u64 * s.1 as u64),
                )
            }),
            FrameSizes::Range { min, max, step } => Some((
                snap(target.0, min.0, max.0, step.0),
                snap(target.1, min.1, max.1, step.1),
            )),
            FrameSizes::Unknown => Some(target),
        }
    }
}

impl fmt::Display for FrameSizes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FrameSizes::Discrete(v) if v.is_empty() => f.write_str("no sizes"),
            FrameSizes::Discrete(v) => {
                let s: Vec<String> = v.iter().map(|(w, h)| format!("{w}x{h}")).collect();
                f.write_str(&s.join(", "))
            }
            FrameSizes::Range { min, max, step } => write!(
                f,
                "{}x{} to {}x{} in steps of {}x{}",
                min.0, min.1, max.0, max.1, step.0, step.1
            ),
            FrameSizes::Unknown => f.write_str("sizes not enumerated"),
        }
    }
}

/// One pixel format a device offers, with its sizes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Offered {
    /// FourCC.
    pub fourcc: u32,
    /// The sizes offered in this format.
    pub sizes: FrameSizes,
}

/// What the user asked for (`None`: let [`choose`] decide).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FormatRequest {
    /// Pixel format.
    pub format: Option<PixelFormat>,
    /// Width and height.
    pub size: Option<(u32, u32)>,
}

impl fmt::Display for FormatRequest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.format {
            Some(p) => write!(f, "{p}")?,
            None => f.write_str("any of RGB24, YUYV, MJPEG")?,
        }
        match self.size {
            Some((w, h)) => write!(f, " at {w}x{h}"),
            None => write!(
                f,
                " at any size (nearest {}x{})",
                DEFAULT_SIZE.0, DEFAULT_SIZE.1
            ),
        }
    }
}

/// A format and size to ask the driver for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Choice {
    /// Pixel format.
    pub format: PixelFormat,
    /// Width and height.
    pub size: (u32, u32),
}

/// What the device offers, as text for error messages.
pub fn describe_offered(offered: &[Offered]) -> String {
    if offered.is_empty() {
        return "no capture format".into();
    }
    let parts: Vec<String> = offered
        .iter()
        .map(|o| match PixelFormat::from_fourcc(o.fourcc) {
            Some(p) => format!("{p} ({})", o.sizes),
            None => format!("{} (not supported by pir2)", fourcc_name(o.fourcc)),
        })
        .collect();
    parts.join("; ")
}

/// Pick the format and size to ask for (see the module docs).
pub fn choose(device: &str, offered: &[Offered], req: &FormatRequest) -> Result<Choice> {
    let fail = || Error::CameraFormat {
        device: device.to_string(),
        asked: req.to_string(),
        offered: describe_offered(offered),
    };
    let mut candidates: Vec<(PixelFormat, &FrameSizes)> = offered
        .iter()
        .filter_map(|o| PixelFormat::from_fourcc(o.fourcc).map(|p| (p, &o.sizes)))
        .filter(|(p, _)| req.format.is_none_or(|f| f == *p))
        .collect();
    candidates.sort_by_key(|(p, _)| p.rank());
    let best = match req.size {
        Some(size) => candidates
            .iter()
            .find(|(_, s)| s.offers(size))
            .map(|&(format, _)| Choice { format, size }),
        None => candidates
            .iter()
            .filter_map(|&(format, s)| s.nearest(DEFAULT_SIZE).map(|size| Choice { format, size }))
            .min_by_key(|c| {
                (
                    distance(c.size, DEFAULT_SIZE),
                    std::cmp::Reverse(c.size.0 as u64 * c.size.1 as u64),
                    c.format.rank(),
                )
            }),
    };
    best.ok_or_else(fail)
}

/// The format the driver settled on (after `VIDIOC_S_FMT`), which the camera uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Negotiated {
    /// Pixel format.
    pub format: PixelFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bytes per row of an uncompressed format (0 for MJPEG).
    pub bytesperline: u32,
    /// Bytes of one frame buffer as the driver sized it.
    pub sizeimage: u32,
}

impl fmt::Display for Negotiated {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}x{}", self.format, self.width, self.height)
    }
}

/// Check the driver's answer to `VIDIOC_S_FMT` for `asked`: the driver may change the size
/// or the format; whatever it chose is used if this crate converts it, with a consistent
/// row stride. Otherwise one [`Error::CameraFormat`] naming what was asked and what the
/// driver gave.
pub fn accept(device: &str, asked: &Choice, got: &sys::PixFormat) -> Result<Negotiated> {
    let fail = |why: String| Error::CameraFormat {
        device: device.to_string(),
        asked: format!("{} {}x{}", asked.format, asked.size.0, asked.size.1),
        offered: format!(
            "the driver set {} {}x{} (bytes per line {}): {why}",
            fourcc_name(got.pixelformat),
            got.width,
            got.height,
            got.bytesperline
        ),
    };
    let format = PixelFormat::from_fourcc(got.pixelformat)
        .ok_or_else(|| fail("a format pir2 does not convert".into()))?;
    if got.width == 0 || got.height == 0 {
        return Err(fail("an empty frame size".into()));
    }
    if format == PixelFormat::Yuyv && got.width % 2 != 0 {
        return Err(fail("an odd width, which YUYV cannot have".into()));
    }
    let bytesperline = match format.bytes_per_pixel() {
        Some(bpp) => {
            let min = got
                .width
                .checked_mul(bpp)
                .ok_or_else(|| fail("a row too long".into()))?;
            match got.bytesperline {
                0 => min,
                b if b < min => return Err(fail(format!("rows shorter than {min} bytes"))),
                b => b,
            }
        }
        None => 0,
    };
    Ok(Negotiated {
        format,
        width: got.width,
        height: got.height,
        bytesperline,
        sizeimage: got.sizeimage,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn discrete(fourcc: u32, sizes: &[(u32, u32)]) -> Offered {
        Offered {
            fourcc,
            sizes: FrameSizes::Discrete(sizes.to_vec()),
        }
    }

    fn req(format: Option<PixelFormat>, size: Option<(u32, u32)>) -> FormatRequest {
        FormatRequest { format, size }
    }

    /// A UVC webcam offering MJPEG at 1280x720 and YUYV at 640x480.
    fn uvc() -> Vec<Offered> {
        vec![
            discrete(sys::PIX_FMT_MJPEG, &[(1280, 720)]),
            discrete(sys::PIX_FMT_YUYV, &[(640, 480)]),
        ]
    }

    #[test]
    fn a_uvc_webcam_gets_yuyv_by_default_and_mjpeg_for_its_large_size() {
        let dev = uvc();
        let c = choose("/dev/video0", &dev, &req(None, None)).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Yuyv,
                size: (640, 480)
            }
        );
        let c = choose("/dev/video0", &dev, &req(None, Some((1280, 720)))).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Mjpeg,
                size: (1280, 720)
            }
        );
        let c = choose("/dev/video0", &dev, &req(Some(PixelFormat::Mjpeg), None)).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Mjpeg,
                size: (1280, 720)
            }
        );
        // YUYV is not offered at 1280x720: one error naming the device, the ask and the offer.
        let e = choose(
            "/dev/video0",
            &dev,
            &req(Some(PixelFormat::Yuyv), Some((1280, 720))),
        )
        .unwrap_err();
        let m = e.to_string();
        for part in [
            "/dev/video0",
            "YUYV at 1280x720",
            "MJPEG (1280x720)",
            "YUYV (640x480)",
        ] {
            assert!(m.contains(part), "`{part}` missing: {m}");
        }
    }

    #[test]
    fn equally_good_formats_follow_the_preference_and_sizes_snap_to_the_nearest() {
        // MJPEG and YUYV both at 640x480: the uncompressed format wins.
        let dev = vec![
            discrete(sys::PIX_FMT_MJPEG, &[(1920, 1080), (640, 480), (320, 240)]),
            discrete(sys::PIX_FMT_YUYV, &[(640, 480), (320, 240)]),
        ];
        let c = choose("cam", &dev, &req(None, None)).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Yuyv,
                size: (640, 480)
            }
        );
        // No 640x480: the nearest offered size (by |dw| + |dh|), from any format.
        let dev = vec![
            discrete(sys::PIX_FMT_MJPEG, &[(1280, 720), (800, 600)]),
            discrete(sys::PIX_FMT_YUYV, &[(320, 240), (160, 120)]),
        ];
        let c = choose("cam", &dev, &req(None, None)).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Mjpeg,
                size: (800, 600)
            }
        );
        // A stepwise range: the target snapped onto its steps; exact sizes only on steps.
        let dev = vec![Offered {
            fourcc: sys::PIX_FMT_RGB24,
            sizes: FrameSizes::Range {
                min: (48, 32),
                max: (4096, 2160),
                step: (16, 8),
            },
        }];
        let c = choose("cam", &dev, &req(None, None)).unwrap();
        assert_eq!(
            c,
            Choice {
                format: PixelFormat::Rgb24,
                size: (640, 480)
            }
        );
        assert!(choose("cam", &dev, &req(None, Some((1024, 768)))).is_ok());
        assert!(choose("cam", &dev, &req(None, Some((1000, 768)))).is_err());
        let small = vec![Offered {
            fourcc: sys::PIX_FMT_YUYV,
            sizes: FrameSizes::Range {
                min: (64, 64),
                max: (320, 200),
                step: (1, 1),
            },
        }];
        let c = choose("cam", &small, &req(None, None)).unwrap();
        assert_eq!(c.size, (320, 200));
        // A driver that does not enumerate sizes: the ask (or the default) goes to S_FMT.
        let dev = vec![Offered {
            fourcc: sys::PIX_FMT_YUYV,
            sizes: FrameSizes::Unknown,
        }];
        assert_eq!(
            choose("cam", &dev, &req(None, None)).unwrap().size,
            DEFAULT_SIZE
        );
        assert_eq!(
            choose("cam", &dev, &req(None, Some((1024, 576))))
                .unwrap()
                .size,
            (1024, 576)
        );
    }

    #[test]
    fn a_device_without_a_supported_format_is_one_error_naming_what_it_offers() {
        let dev = vec![
            discrete(sys::fourcc(b"H264"), &[(1920, 1080)]),
            discrete(sys::fourcc(b"GREY"), &[(640, 480)]),
        ];
        let e = choose("/dev/video7", &dev, &req(None, None)).unwrap_err();
        assert!(matches!(e, Error::CameraFormat { .. }), "{e:?}");
        let m = e.to_string();
        for part in [
            "/dev/video7",
            "any of RGB24, YUYV, MJPEG",
            "H264 (not supported by pir2)",
            "GREY (not supported by pir2)",
        ] {
            assert!(m.contains(part), "`{part}` missing: {m}");
        }
        // Asking for a supported format the device lacks, and a device offering nothing.
        let e = choose(
            "/dev/video0",
            &uvc()[..1],
            &req(Some(PixelFormat::Yuyv), None),
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("cannot capture YUYV at any size"),
            "{e}"
        );
        let e = choose("/dev/video0", &[], &req(None, None)).unwrap_err();
        assert!(e.to_string().contains("no capture format"), "{e}");
        let e = choose(
            "/dev/video0",
            &[discrete(sys::PIX_FMT_YUYV, &[])],
            &req(None, None),
        )
        .unwrap_err();
        assert!(e.to_string().contains("YUYV (no sizes)"), "{e}");
    }

    fn pix(fourcc: u32, w: u32, h: u32, bpl: u32) -> sys::PixFormat {
        sys::PixFormat {
            width: w,
            height: h,
            pixelformat: fourcc,
            bytesperline: bpl,
            sizeimage: bpl * h,
            ..Default::default()
        }
    }

    #[test]
    fn the_drivers_answer_is_used_when_convertible_and_refused_by_name_otherwise() {
        let asked = Choice {
            format: PixelFormat::Yuyv,
            size: (640, 480),
        };
        // The driver changed the size: used as given; a padded stride is kept.
        let n = accept("cam", &asked, &pix(sys::PIX_FMT_YUYV, 320, 240, 704)).unwrap();
        assert_eq!(
            (n.format, n.width, n.height, n.bytesperline),
            (PixelFormat::Yuyv, 320, 240, 704)
        );
        // Stride 0 (some drivers): the packed stride.
        let n = accept("cam", &asked, &pix(sys::PIX_FMT_YUYV, 640, 480, 0)).unwrap();
        assert_eq!(n.bytesperline, 1280);
        // The driver switched to another supported format: used.
        let n = accept("cam", &asked, &pix(sys::PIX_FMT_MJPEG, 640, 480, 0)).unwrap();
        assert_eq!((n.format, n.bytesperline), (PixelFormat::Mjpeg, 0));
        // Switched to one we cannot convert, an empty size, rows too short: errors.
        let e = accept(
            "/dev/video2",
            &asked,
            &pix(sys::fourcc(b"NV12"), 640, 480, 640),
        )
        .unwrap_err();
        let m = e.to_string();
        assert!(
            m.contains("/dev/video2") && m.contains("YUYV 640x480") && m.contains("NV12"),
            "{m}"
        );
        assert!(accept("cam", &asked, &pix(sys::PIX_FMT_YUYV, 0, 480, 0)).is_err());
        assert!(accept("cam", &asked, &pix(sys::PIX_FMT_YUYV, 640, 480, 1000)).is_err());
    }

    #[test]
    fn formats_and_sizes_parse_from_the_command_line() {
        assert_eq!("MJPEG".parse::<PixelFormat>().unwrap(), PixelFormat::Mjpeg);
        assert_eq!("yuyv".parse::<PixelFormat>().unwrap(), PixelFormat::Yuyv);
        assert!("h264".parse::<PixelFormat>().is_err());
        assert_eq!(parse_size("1280x720").unwrap(), (1280, 720));
        for bad in ["1280", "0x480", "ax480", "640x-1"] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
        assert_eq!(fourcc_name(sys::PIX_FMT_MJPEG), "MJPG");
    }
}
