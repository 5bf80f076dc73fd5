//! Camera pixel formats to HWC `u8` RGB.
//!
//! - **YUYV** (packed 4:2:2, `Y0 U Y1 V` for two horizontally adjacent pixels sharing one
//!   chroma pair) is read as ITU-R BT.601 with limited ("studio") range, which is what UVC
//!   cameras send and what OpenCV's `COLOR_YUV2RGB_YUYV` assumes:
//!   `R = 1.164 (Y − 16) + 1.596 (V − 128)`,
//!   `G = 1.164 (Y − 16) − 0.813 (V − 128) − 0.391 (U − 128)`,
//!   `B = 1.164 (Y − 16) + 2.018 (U − 128)`, rounded and clamped to `0..=255`, computed in
//!   20-bit fixed point; luma below the black level 16 (the format's foot-room) counts as
//!   16, as in OpenCV. Checked against OpenCV on a committed fixture (see the tests): equal
//!   on every value.
//! - **MJPEG** frames are JPEG images; UVC cameras commonly omit the Huffman tables (the
//!   AVI MJPEG convention), so when a frame has no `DHT` segment before its scan, the JPEG
//!   standard's example tables (ITU T.81, Annex K.3) are inserted before decoding. A frame
//!   that does not start with SOI, has no EOI (a truncated transfer), fails to decode, or
//!   decodes to another size than negotiated is an error.
//! - **RGB24** rows are copied without their padding.
//!
//! Every function checks the buffer against the negotiated geometry first: a short buffer
//! is an error, never a partially old image.

/// Why a frame could not be converted (the camera wraps it with the device name).
pub type ConvertResult<T> = std::result::Result<T, String>;

fn check_len(data: &[u8], stride: usize, row: usize, height: usize) -> ConvertResult<()> {
    let need = stride * (height - 1) + row;
    if data.len() < need {
        return Err(format!(
            "short frame: {} bytes, {need} needed for {height} rows of stride {stride}",
            data.len()
        ));
    }
    Ok(())
}

const SHIFT: u32 = 20;
const HALF: i32 = 1 << (SHIFT - 1);
const fn fix(c: f64) -> i32 {
    // Round half away from zero (const-compatible `f64::round`).
    let s = c * (1u32 << SHIFT) as f64;
    if s >= 0.0 {
        (s + 0.5) as i32
    } else {
        (s - 0.5) as i32
    }
}
const CY: i32 = fix(1.164);
const CVR: i32 = fix(1.596);
const CVG: i32 = fix(-0.813);
const CUG: i32 = fix(-0.391);
const CUB: i32 = fix(2.018);

#[inline]
fn clamp_u8(v: i32) -> u8 {
    (v >> SHIFT).clamp(0, 255) as u8
}

/// YUYV (`width` even, rows `stride` bytes apart) to packed RGB, appended to `out`.
pub fn yuyv_to_rgb(
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
    out: &mut Vec<u8>,
) -> ConvertResult<()> {
    if width == 0 || height == 0 || width % 2 != 0 || stride < 2 * width {
        return Err(format!(
            "YUYV geometry {width}x{height} with stride {stride} (width must be even and > 0)"
        ));
    }
    check_len(data, stride, 2 * width, height)?;
    out.reserve(width * height * 3);
    for row in data.chunks(stride).take(height) {
        for px in row[..2 * width].chunks_exact(4) {
            let (u, v) = (px[1] as i32 - 128, px[3] as i32 - 128);
            let r = HALF + CVR * v;
            let g = HALF + CVG * v + CUG * u;
            let b = HALF + CUB * u;
            for y in [px[0], px[2]] {
                let y = (y as i32 - 16).max(0) * CY;
                out.extend_from_slice(&[clamp_u8(y + r), clamp_u8(y + g), clamp_u8(y + b)]);
            }
        }
    }
    Ok(())
}

/// RGB24 rows (`stride` bytes apart) to packed RGB, appended to `out`.
pub fn rgb24_rows(
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
    out: &mut Vec<u8>,
) -> ConvertResult<()> {
    if width == 0 || height == 0 || stride < 3 * width {
        return Err(format!(
            "RGB24 geometry {width}x{height} with stride {stride}"
        ));
    }
    check_len(data, stride, 3 * width, height)?;
    out.reserve(width * height * 3);
    for row in data.chunks(stride).take(height) {
        out.extend_from_slice(&row[..3 * width]);
    }
    Ok(())
}

/// The `DHT` segment of the JPEG standard's example Huffman tables (ITU T.81 Annex K.3:
/// luminance DC and AC as tables 0, chrominance DC and AC as tables 1).
fn standard_dht() -> Vec<u8> {
    // (class/id byte, code counts per length 1..=16, symbols)
    const DC_COUNTS_0: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
    const DC_COUNTS_1: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
    const DC_SYMBOLS: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
    const AC_COUNTS_0: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d];
    const AC_COUNTS_1: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
    const AC_SYMBOLS_0: [u8; 162] = [
        0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61,
        0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52,
        0xd1, 0xf0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25,
        0x26, 0x27, 0x28, 0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45,
        0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64,
        0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83,
        0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99,
        0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6,
        0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3,
        0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8,
        0xe9, 0xea, 0xf1, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    const AC_SYMBOLS_1: [u8; 162] = [
        0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61,
        0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33,
        0x52, 0xf0, 0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18,
        0x19, 0x1a, 0x26, 0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44,
        0x45, 0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63,
        0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a,
        0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97,
        0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4,
        0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca,
        0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7,
        0xe8, 0xe9, 0xea, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    let tables: [(u8, &[u8; 16], &[u8]); 4] = [
        (0x00, &DC_COUNTS_0, &DC_SYMBOLS),
        (0x10, &AC_COUNTS_0, &AC_SYMBOLS_0),
        (0x01, &DC_COUNTS_1, &DC_SYMBOLS),
        (0x11, &AC_COUNTS_1, &AC_SYMBOLS_1),
    ];
    let body: usize = tables.iter().map(|(_, c, s)| 1 + c.len() + s.len()).sum();
    let mut seg = vec![0xff, 0xc4];
    seg.extend_from_slice(&((body + 2) as u16).to_be_bytes());
    for (id, counts, symbols) in tables {
        debug_assert_eq!(
            counts.iter().map(|&c| c as usize).sum::<usize>(),
            symbols.len()
        );
        seg.push(id);
        seg.extend_from_slice(counts);
        seg.extend_from_slice(symbols);
    }
    seg
}

/// Where the first scan starts (its `SOS` marker) and whether a `DHT` segment precedes it.
fn scan_start(data: &[u8]) -> ConvertResult<(usize, bool)> {
    let mut i = 2;
    let mut dht = false;
    loop {
        // Fill bytes (0xff) may precede a marker.
        while i + 1 < data.len() && data[i] == 0xff && data[i + 1] == 0xff {
            i += 1;
        }
        if i + 4 > data.len() || data[i] != 0xff {
            return Err(format!("bad JPEG header at byte {i}"));
        }
        let marker = data[i + 1];
        match marker {
            0xda => return Ok((i, dht)),
            0xd0..=0xd9 | 0x01 => i += 2,
            _ => {
                let len = u16::from_be_bytes([data[i + 2], data[i + 3]]) as usize;
                if len < 2 {
                    return Err(format!("bad JPEG segment length {len} at byte {i}"));
                }
                dht |= marker == 0xc4;
                i += 2 + len;
            }
        }
    }
}

/// Decode one MJPEG frame of the negotiated `width`×`height` into packed RGB, appended to
/// `out` (see the module docs for what is refused).
pub fn decode_mjpeg(
    data: &[u8],
    width: usize,
    height: usize,
    out: &mut Vec<u8>,
) -> ConvertResult<()> {
    if data.len() < 4 || data[..2] != [0xff, 0xd8] {
        return Err("not a JPEG frame (no start-of-image marker)".into());
    }
    // Drivers may pad a frame after its end-of-image marker; a frame without one was cut
    // short in transfer.
    let end = data
        .windows(2)
        .rposition(|w| w == [0xff, 0xd9])
        .ok_or("truncated JPEG frame (no end-of-image marker)")?;
    let data = &data[..end + 2];
    let (sos, has_dht) = scan_start(data)?;
    let patched;
    let jpeg = if has_dht {
        data
    } else {
        let dht = standard_dht();
        let mut v = Vec::with_capacity(data.len() + dht.len());
        v.extend_from_slice(&data[..sos]);
        v.extend_from_slice(&dht);
        v.extend_from_slice(&data[sos..]);
        patched = v;
        &patched
    };
    let img = image::load_from_memory_with_format(jpeg, image::ImageFormat::Jpeg)
        .map_err(|e| format!("corrupt JPEG frame: {e}"))?;
    let rgb = img.to_rgb8();
    let (w, h) = rgb.dimensions();
    if (w as usize, h as usize) != (width, height) {
        return Err(format!(
            "JPEG frame is {w}x{h}, the negotiated size is {width}x{height}"
        ));
    }
    out.extend_from_slice(rgb.as_raw());
    Ok(())
}
