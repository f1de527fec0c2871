//! Loading images as 8-bit grey.
//!
//! Files are read with `std::fs`, not `imread`: `imread` answers a missing file, a
//! directory and a corrupt PNG alike with an empty `Mat`, while reading the bytes
//! ourselves lets each failure say what it was. PNGs are decoded by the `png` crate
//! ([`decode_png`]: libpng would print its own lines on stderr for a corrupt one),
//! other formats by `imdecode`. Both keep 16 bits, so that a 16-bit depth PNG is
//! recognised and refused instead of being silently scaled down to 8 bits.

use std::path::Path;

use opencv::core::{self, Mat, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

use crate::error::{CvContext, VisionError};

/// An 8-bit, single-channel, continuous OpenCV image.
#[derive(Debug)]
pub struct GrayImage {
    mat: Mat,
}

impl GrayImage {
    /// Wraps a `Mat` that must be non-empty `CV_8UC1`; a non-continuous view is copied.
    pub fn from_mat(mat: Mat) -> Result<Self, VisionError> {
        if mat.empty() || mat.rows() <= 0 || mat.cols() <= 0 {
            return Err(VisionError::InvalidImage("empty image".into()));
        }
        if mat.typ() != core::CV_8UC1 {
            return Err(VisionError::InvalidImage(format!(
                "expected an 8-bit single-channel Mat, got depth {} with {} channels",
                mat.depth(),
                mat.channels()
            )));
        }
        let mat = if mat.is_continuous() {
            mat
        } else {
            mat.try_clone().cv("Mat::clone")?
        };
        Ok(GrayImage { mat })
    }

    /// Builds an image from row-major grey values.
    pub fn from_raw(width: u32, height: u32, pixels: &[u8]) -> Result<Self, VisionError> {
        let n = width as usize * height as usize;
        if n == 0 || pixels.len() != n {
            return Err(VisionError::InvalidImage(format!(
                "{width}x{height} image needs {n} bytes, got {}",
                pixels.len()
            )));
        }
        let rows = i32::try_from(height)
            .map_err(|_| VisionError::InvalidImage(format!("height {height} too large")))?;
        let cols = i32::try_from(width)
            .map_err(|_| VisionError::InvalidImage(format!("width {width} too large")))?;
        let view =
            Mat::new_rows_cols_with_data(rows, cols, pixels).cv("Mat::new_rows_cols_with_data")?;
        GrayImage::from_mat(view.try_clone().cv("Mat::clone")?)
    }

    pub fn width(&self) -> u32 {
        self.mat.cols() as u32
    }

    pub fn height(&self) -> u32 {
        self.mat.rows() as u32
    }

    /// The underlying `CV_8UC1` Mat.
    pub fn mat(&self) -> &Mat {
        &self.mat
    }

    /// Row-major pixel bytes (`width * height` of them).
    pub fn pixels(&self) -> &[u8] {
        // The constructor guarantees a continuous CV_8UC1 Mat, for which this cannot fail.
        self.mat.data_bytes().unwrap_or(&[])
    }

    /// Bilinearly interpolated grey value at a pixel position (OpenCV convention: the
    /// centre of the top-left pixel is (0, 0)); `None` outside the image.
    pub fn sample(&self, u: f64, v: f64) -> Option<f64> {
        let (w, h) = (self.width() as usize, self.height() as usize);
        if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64) {
            return None;
        }
        let (x0, y0) = (u.floor() as usize, v.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (u - x0 as f64, v - y0 as f64);
        let p = self.pixels();
        let at = |x: usize, y: usize| f64::from(p[y * w + x]);
        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }

    /// Variance of the 3x3 Laplacian: a cheap sharpness measure (in grey levels²).
    pub fn laplacian_variance(&self) -> Result<f64, VisionError> {
        let mut lap = Mat::default();
        imgproc::laplacian(
            &self.mat,
            &mut lap,
            core::CV_64F,
            3,
            1.0,
            0.0,
            core::BORDER_DEFAULT,
        )
        .cv("laplacian")?;
        let mut mean = Vector::<f64>::new();
        let mut std = Vector::<f64>::new();
        core::mean_std_dev(&lap, &mut mean, &mut std, &core::no_array()).cv("meanStdDev")?;
        let s = std.get(0).cv("meanStdDev result")?;
        Ok(s * s)
    }
}

/// Largest image decoded, in pixels: 50 Mpx, several times any camera of the
/// platform. A header claiming more is refused before decoding (a PNG that claims
/// 32000x32000 pixels would otherwise take gigabytes and minutes to decode).
pub const MAX_IMAGE_PIXELS: u64 = 50_000_000;

/// How many bytes of a file [`image_file_size`] reads to find the header.
const HEADER_READ_LIMIT: u64 = 256 * 1024;

/// Whether `bytes` start with the PNG signature.
fn is_png(bytes: &[u8]) -> bool {
    bytes.starts_with(&[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A])
}

/// Width and height as an encoded image's header states them, without decoding:
/// PNG's IHDR (bytes 16..24) or a JPEG's SOF segment. `None` when the bytes are
/// neither, or the JPEG's SOF is not within `bytes`.
pub fn header_size(bytes: &[u8]) -> Option<(u32, u32)> {
    if bytes.len() >= 24 && is_png(bytes) && &bytes[12..16] == b"IHDR" {
        let be =
            |k: usize| u32::from_be_bytes([bytes[k], bytes[k + 1], bytes[k + 2], bytes[k + 3]]);
        return Some((be(16), be(20)));
    }
    if bytes.len() >= 4 && bytes[0] == 0xFF && bytes[1] == 0xD8 {
        let mut k = 2;
        while k + 4 <= bytes.len() {
            if bytes[k] != 0xFF {
                return None;
            }
            let marker = bytes[k + 1];
            match marker {
                // Fill byte before a marker.
                0xFF => {
                    k += 1;
                    continue;
                }
                // Stand-alone markers (no length).
                0x01 | 0xD0..=0xD7 => {
                    k += 2;
                    continue;
                }
                // End of image or start of scan before any frame header.
                0xD9 | 0xDA => return None,
                _ => {}
            }
            let len = usize::from(u16::from_be_bytes([bytes[k + 2], bytes[k + 3]]));
            let is_sof = matches!(marker, 0xC0..=0xCF) && !matches!(marker, 0xC4 | 0xC8 | 0xCC);
            if is_sof {
                if k + 9 > bytes.len() {
                    return None;
                }
                let h = u16::from_be_bytes([bytes[k + 5], bytes[k + 6]]);
                let w = u16::from_be_bytes([bytes[k + 7], bytes[k + 8]]);
                return Some((u32::from(w), u32::from(h)));
            }
            if len < 2 {
                return None;
            }
            k += 2 + len;
        }
    }
    None
}

/// For a PNG: that its chunks chain from the signature to `IEND` inside the
/// bytes, with image data on the way (lengths only; nothing is decompressed).
/// A file cut short is refused here, with where it ends, rather than by libpng,
/// which would also print its own line on stderr. Other formats pass.
pub fn png_chunks_complete(bytes: &[u8]) -> Result<(), String> {
    if !is_png(bytes) {
        return Ok(());
    }
    let mut k = 8usize;
    let mut image_data = false;
    loop {
        if k + 8 > bytes.len() {
            return Err(format!(
                "the PNG is cut short: it ends at byte {} without its IEND chunk",
                bytes.len()
            ));
        }
        let len = u32::from_be_bytes([bytes[k], bytes[k + 1], bytes[k + 2], bytes[k + 3]]) as usize;
        let kind = &bytes[k + 4..k + 8];
        let end = k.saturating_add(12).saturating_add(len);
        if end > bytes.len() {
            return Err(format!(
                "the PNG is cut short: its {} chunk at byte {k} needs {len} bytes of data, the file ends at byte {}",
                String::from_utf8_lossy(kind),
                bytes.len()
            ));
        }
        match kind {
            b"IDAT" => image_data = true,
            b"IEND" if !image_data => {
                return Err("the PNG has no image data (IDAT) before its end".into());
            }
            b"IEND" => return Ok(()),
            _ => {}
        }
        k = end;
    }
}

/// A PNG decoded by the `png` crate, not by OpenCV's libpng: libpng answers a
/// corrupt file (bad checksums, broken compressed data, a fake) by printing its own
/// lines on stderr besides failing, where this returns the reason as an error that
/// names the file. Palette and low-bit images are expanded to 8 bits; 16-bit
/// samples are kept, big-endian as PNG stores them.
pub(crate) struct DecodedPng {
    pub width: u32,
    pub height: u32,
    /// 1 grey, 2 grey + alpha, 3 RGB, 4 RGBA.
    pub channels: usize,
    pub sixteen_bit: bool,
    /// Row-major samples, no padding between rows.
    pub data: Vec<u8>,
}

/// Decodes `bytes` when they start with the PNG signature (`None` otherwise).
/// The caller has checked the size the header states.
pub(crate) fn decode_png(
    bytes: &[u8],
    source_name: &str,
) -> Result<Option<DecodedPng>, VisionError> {
    if !is_png(bytes) {
        return Ok(None);
    }
    let corrupt = |reason: String| VisionError::CorruptImage {
        source_name: source_name.to_owned(),
        reason,
    };
    png_chunks_complete(bytes).map_err(corrupt)?;
    // Eight bytes per pixel is RGBA at 16 bits, the most a PNG pixel takes.
    let limits = png::Limits {
        bytes: usize::try_from(MAX_IMAGE_PIXELS * 8).unwrap_or(usize::MAX),
    };
    let mut decoder = png::Decoder::new_with_limits(std::io::Cursor::new(bytes), limits);
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder
        .read_info()
        .map_err(|e| corrupt(format!("PNG decoder: {e}")))?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| corrupt("the PNG's stated size overflows memory".into()))?;
    let mut data = vec![0u8; size];
    let info = reader
        .next_frame(&mut data)
        .map_err(|e| corrupt(format!("PNG decoder: {e}")))?;
    data.truncate(info.buffer_size());
    let channels = info.color_type.samples();
    let sixteen_bit = info.bit_depth == png::BitDepth::Sixteen;
    let expected =
        info.width as usize * info.height as usize * channels * (1 + sixteen_bit as usize);
    if data.len() != expected {
        return Err(corrupt(format!(
            "PNG decoder gave {} bytes for {}x{} with {channels} channel(s), expected {expected}",
            data.len(),
            info.width,
            info.height
        )));
    }
    Ok(Some(DecodedPng {
        width: info.width,
        height: info.height,
        channels,
        sixteen_bit,
        data,
    }))
}

impl DecodedPng {
    /// As 8-bit grey: colour by OpenCV's `cvtColor` (as `imdecode` + `cvtColor`
    /// gave before), alpha dropped; 16 bits refused.
    fn to_gray(&self, source_name: &str) -> Result<GrayImage, VisionError> {
        if self.sixteen_bit {
            return Err(VisionError::SixteenBit {
                source_name: source_name.to_owned(),
            });
        }
        let grey: Vec<u8>;
        let pixels = match self.channels {
            1 => &self.data,
            2 => {
                grey = self.data.iter().step_by(2).copied().collect();
                &grey
            }
            3 | 4 => {
                let rows = i32::try_from(self.height).map_err(|_| {
                    VisionError::InvalidImage(format!("height {} too large", self.height))
                })?;
                let flat = Mat::new_rows_cols_with_data(
                    rows,
                    (self.data.len() / self.height as usize) as i32,
                    &self.data,
                )
                .cv("Mat::new_rows_cols_with_data")?;
                let colour = flat
                    .reshape(self.channels as i32, rows)
                    .cv("Mat::reshape")?;
                let code = if self.channels == 3 {
                    imgproc::COLOR_RGB2GRAY
                } else {
                    imgproc::COLOR_RGBA2GRAY
                };
                let mut g = Mat::default();
                imgproc::cvt_color(&colour, &mut g, code, 0).cv("cvtColor")?;
                return GrayImage::from_mat(g);
            }
            c => {
                return Err(VisionError::UnsupportedImage {
                    source_name: source_name.to_owned(),
                    what: format!("{c} channels"),
                });
            }
        };
        GrayImage::from_raw(self.width, self.height, pixels)
    }
}

/// The size an image file's header states (see [`header_size`]), reading at most
/// its first 256 KiB; `None` when the header is not PNG or JPEG or not found there.
pub fn image_file_size(path: &Path) -> Result<Option<(u32, u32)>, VisionError> {
    use std::io::Read;
    let io = |source| VisionError::Io {
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut head = Vec::new();
    file.take(HEADER_READ_LIMIT)
        .read_to_end(&mut head)
        .map_err(io)?;
    Ok(header_size(&head))
}

/// Refuses a stated size above [`MAX_IMAGE_PIXELS`], or different from `expected`
/// (the camera intrinsics' width and height) when given.
pub(crate) fn check_stated_size(
    source_name: &str,
    (width, height): (u32, u32),
    expected: Option<(u32, u32)>,
) -> Result<(), VisionError> {
    if u64::from(width) * u64::from(height) > MAX_IMAGE_PIXELS || width == 0 || height == 0 {
        return Err(VisionError::ImageTooLarge {
            source_name: source_name.to_owned(),
            width,
            height,
            max_pixels: MAX_IMAGE_PIXELS,
        });
    }
    if let Some((ew, eh)) = expected
        && (width, height) != (ew, eh)
    {
        return Err(VisionError::ImageSizeMismatch {
            source_name: source_name.to_owned(),
            width,
            height,
            expected_width: ew,
            expected_height: eh,
        });
    }
    Ok(())
}

/// Checks an image file's header against the camera intrinsics' size and the pixel
/// cap without decoding it. A file whose header is neither PNG nor JPEG passes here
/// (decoding it will say what it is).
pub fn check_image_file(path: &Path, width: u32, height: u32) -> Result<(), VisionError> {
    match image_file_size(path)? {
        Some(size) => check_stated_size(&path.display().to_string(), size, Some((width, height))),
        None => Ok(()),
    }
}

/// Loads an image file as 8-bit grey. Colour images are converted (BGR weights);
/// 16-bit images are refused rather than rescaled. A header claiming more than
/// [`MAX_IMAGE_PIXELS`] is refused before decoding.
pub fn load_gray(path: &Path) -> Result<GrayImage, VisionError> {
    load_gray_checked(path, None)
}

/// [`load_gray`] for an image that must be `width` x `height` (the camera
/// intrinsics' size): the header is checked before decoding, and the decoded
/// image again.
pub fn load_gray_sized(path: &Path, width: u32, height: u32) -> Result<GrayImage, VisionError> {
    load_gray_checked(path, Some((width, height)))
}

fn load_gray_checked(path: &Path, expected: Option<(u32, u32)>) -> Result<GrayImage, VisionError> {
    let bytes = std::fs::read(path).map_err(|source| VisionError::Io {
        path: path.to_owned(),
        source,
    })?;
    let name = path.display().to_string();
    if let Some(size) = header_size(&bytes) {
        check_stated_size(&name, size, expected)?;
    }
    let img = decode_gray(&bytes, &name)?;
    check_stated_size(&name, (img.width(), img.height()), expected)?;
    Ok(img)
}

/// Decodes an encoded image (PNG, JPEG, ...) held in memory as 8-bit grey;
/// `source_name` is used in error messages.
/// A header claiming more than [`MAX_IMAGE_PIXELS`] is refused before decoding.
pub fn decode_gray(bytes: &[u8], source_name: &str) -> Result<GrayImage, VisionError> {
    let corrupt = |reason: &str| VisionError::CorruptImage {
        source_name: source_name.to_owned(),
        reason: reason.to_owned(),
    };
    if bytes.is_empty() {
        return Err(corrupt("the file is empty"));
    }
    if let Some(size) = header_size(bytes) {
        check_stated_size(source_name, size, None)?;
    }
    if let Some(png) = decode_png(bytes, source_name)? {
        return png.to_gray(source_name);
    }
    let buf = Vector::<u8>::from_slice(bytes);
    // OpenCV's decoders report failure as an empty Mat, or sometimes throw.
    let mat = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_UNCHANGED)
        .map_err(|e| corrupt(&format!("decoder error: {}", e.message)))?;
    if mat.empty() {
        return Err(corrupt("no OpenCV decoder accepts these bytes"));
    }
    match mat.depth() {
        core::CV_8U => {}
        core::CV_16U => {
            return Err(VisionError::SixteenBit {
                source_name: source_name.to_owned(),
            });
        }
        d => {
            return Err(VisionError::UnsupportedImage {
                source_name: source_name.to_owned(),
                what: format!("OpenCV depth code {d}, expected 8-bit unsigned"),
            });
        }
    }
    let code = match mat.channels() {
        1 => None,
        3 => Some(imgproc::COLOR_BGR2GRAY),
        4 => Some(imgproc::COLOR_BGRA2GRAY),
        c => {
            return Err(VisionError::UnsupportedImage {
                source_name: source_name.to_owned(),
                what: format!("{c} channels"),
            });
        }
    };
    let gray = match code {
        None => mat,
        Some(code) => {
            let mut g = Mat::default();
            imgproc::cvt_color(&mat, &mut g, code, 0).cv("cvtColor")?;
            g
        }
    };
    GrayImage::from_mat(gray)
}

#[cfg(test)]
mod header_tests {
    use super::*;

    #[test]
    fn png_and_jpeg_headers_give_the_size_without_decoding() {
        let mut png = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A, 0, 0, 0, 13];
        png.extend_from_slice(b"IHDR");
        png.extend_from_slice(&32000u32.to_be_bytes());
        png.extend_from_slice(&24000u32.to_be_bytes());
        assert_eq!(header_size(&png), Some((32000, 24000)));
        // SOI, an APP0 segment (16 bytes), a fill byte, then SOF2 (progressive).
        let mut jpeg = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10];
        jpeg.extend_from_slice(&[0u8; 14]);
        jpeg.extend_from_slice(&[0xFF, 0xFF, 0xC2, 0x00, 0x11, 8, 0x01, 0xE0, 0x02, 0x80]);
        assert_eq!(header_size(&jpeg), Some((640, 480)));
        // A DHT segment (0xC4) is not a frame header; a scan before any frame is refused.
        let no_sof = [0xFF, 0xD8, 0xFF, 0xC4, 0x00, 0x02, 0xFF, 0xDA, 0x00, 0x02];
        assert_eq!(header_size(&no_sof), None);
        assert_eq!(header_size(b"not an image"), None);
        assert_eq!(header_size(&png[..20]), None);
        let err = decode_gray(&png, "huge.png").unwrap_err();
        assert!(matches!(err, VisionError::ImageTooLarge { .. }), "{err:?}");
        assert!(err.to_string().contains("32000x24000"), "{err}");
    }

    #[test]
    fn a_png_cut_short_is_named_before_decoding() {
        let mut png = Vec::new();
        png.extend_from_slice(&[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A]);
        let chunk = |png: &mut Vec<u8>, kind: &[u8], data: &[u8]| {
            png.extend_from_slice(&(data.len() as u32).to_be_bytes());
            png.extend_from_slice(kind);
            png.extend_from_slice(data);
            png.extend_from_slice(&[0; 4]);
        };
        // 64 x 48, 8-bit grey.
        let mut ihdr = [0u8; 13];
        ihdr[..4].copy_from_slice(&64u32.to_be_bytes());
        ihdr[4..8].copy_from_slice(&48u32.to_be_bytes());
        ihdr[8] = 8;
        chunk(&mut png, b"IHDR", &ihdr);
        chunk(&mut png, b"IDAT", &[0; 100]);
        chunk(&mut png, b"IEND", &[]);
        assert_eq!(png_chunks_complete(&png), Ok(()));
        let cut = &png[..png.len() - 60];
        let e = png_chunks_complete(cut).unwrap_err();
        assert!(e.contains("cut short") && e.contains("IDAT"), "{e}");
        let e = png_chunks_complete(&png[..png.len() - 12]).unwrap_err();
        assert!(e.contains("without its IEND"), "{e}");
        let err = decode_gray(cut, "cut.png").unwrap_err().to_string();
        assert!(
            err.contains("cut.png") && err.contains("cut short"),
            "{err}"
        );
        // Not a PNG: left to the decoders.
        assert_eq!(png_chunks_complete(b"JFIF..."), Ok(()));
    }
}
