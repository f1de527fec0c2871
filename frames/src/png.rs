//! PNG images decoded straight into a frame's bytes (dataset replay).
//!
//! [`PngImage::open`] reads only the PNG header, which is all a [`FrameHeader`]
//! needs; [`PngImage::decode_into`] then decodes the pixels into the caller's
//! buffer, which is the loaned shared-memory sample when used with
//! [`crate::FramePublisher::try_publish_with`]. 8-bit grey becomes
//! [`StreamKind::Gray8`], 8-bit RGB (and palette images) [`StreamKind::Rgb8`],
//! 16-bit grey [`StreamKind::Z16`] (PNG's big-endian samples are swapped to the
//! little-endian of the wire). Alpha channels and 16-bit colour are refused.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use crate::{FrameHeader, FramesError, StreamKind};

/// An opened PNG whose pixels have not been decoded yet.
pub struct PngImage {
    path: PathBuf,
    kind: StreamKind,
    width: u32,
    height: u32,
    reader: png::Reader<BufReader<File>>,
}

impl std::fmt::Debug for PngImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PngImage")
            .field("path", &self.path)
            .field("kind", &self.kind)
            .field("width", &self.width)
            .field("height", &self.height)
            .finish()
    }
}

fn image_err(path: &Path, reason: impl Into<String>) -> FramesError {
    FramesError::Image {
        path: path.to_owned(),
        reason: reason.into(),
    }
}

impl PngImage {
    /// Opens `path` and reads its PNG header.
    pub fn open(path: &Path) -> Result<PngImage, FramesError> {
        let file = File::open(path).map_err(|e| image_err(path, format!("cannot open: {e}")))?;
        let mut decoder = png::Decoder::new(BufReader::new(file));
        decoder.set_transformations(png::Transformations::EXPAND);
        let reader = decoder
            .read_info()
            .map_err(|e| image_err(path, format!("not a readable PNG: {e}")))?;
        let (colour, depth) = reader.output_color_type();
        let kind = match (colour, depth) {
            (png::ColorType::Grayscale, png::BitDepth::Eight) => StreamKind::Gray8,
            (png::ColorType::Rgb, png::BitDepth::Eight) => StreamKind::Rgb8,
            (png::ColorType::Grayscale, png::BitDepth::Sixteen) => StreamKind::Z16,
            (c, d) => {
                return Err(image_err(
                    path,
                    format!(
                        "{c:?} {d:?} PNG: frames are 8-bit grey, 8-bit RGB or 16-bit depth (no alpha)"
                    ),
                ));
            }
        };
        let info = reader.info();
        let (width, height) = (info.width, info.height);
        Ok(PngImage {
            path: path.to_owned(),
            kind,
            width,
            height,
            reader,
        })
    }

    pub fn kind(&self) -> StreamKind {
        self.kind
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// A packed-row header for this image (no intrinsics; fill those in).
    pub fn header(&self) -> FrameHeader {
        FrameHeader::new(self.kind, self.width, self.height)
    }

    /// Decodes the pixels into `buf`, which must be exactly
    /// `width * height * bytes_per_pixel` bytes (packed rows).
    pub fn decode_into(mut self, buf: &mut [u8]) -> Result<(), FramesError> {
        let expected = self.header().payload_len();
        if buf.len() != expected || self.reader.output_buffer_size() != expected {
            return Err(image_err(
                &self.path,
                format!(
                    "decoding needs {} bytes, the frame has {}",
                    self.reader.output_buffer_size(),
                    buf.len()
                ),
            ));
        }
        self.reader
            .next_frame(buf)
            .map_err(|e| image_err(&self.path, format!("corrupt PNG: {e}")))?;
        if self.kind == StreamKind::Z16 {
            for px in buf.chunks_exact_mut(2) {
                px.swap(0, 1);
            }
        }
        Ok(())
    }

    /// Decodes into a new vector (for tests and tools).
    pub fn decode(self) -> Result<Vec<u8>, FramesError> {
        let mut buf = vec![0; self.header().payload_len()];
        self.decode_into(&mut buf)?;
        Ok(buf)
    }
}

/// Writes a frame's packed bytes as a PNG: grey and RGB as 8-bit, depth as 16-bit
/// grey (the wire's little-endian samples swapped to PNG's big-endian). The
/// inverse of [`PngImage::decode`], for recording frames into a dataset and for tests.
pub fn write(
    path: &Path,
    kind: StreamKind,
    width: u32,
    height: u32,
    data: &[u8],
) -> Result<(), FramesError> {
    let expected = FrameHeader::new(kind, width, height).payload_len();
    if data.len() != expected || expected == 0 {
        return Err(image_err(
            path,
            format!(
                "a {width}x{height} {} image needs {expected} bytes, got {}",
                kind.name(),
                data.len()
            ),
        ));
    }
    let file = File::create(path).map_err(|e| image_err(path, format!("cannot create: {e}")))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    let (colour, depth) = match kind {
        StreamKind::Gray8 => (png::ColorType::Grayscale, png::BitDepth::Eight),
        StreamKind::Rgb8 => (png::ColorType::Rgb, png::BitDepth::Eight),
        StreamKind::Z16 => (png::ColorType::Grayscale, png::BitDepth::Sixteen),
    };
    enc.set_color(colour);
    enc.set_depth(depth);
    let fail = |e: png::EncodingError| image_err(path, format!("cannot write PNG: {e}"));
    let mut writer = enc.write_header().map_err(fail)?;
    if kind == StreamKind::Z16 {
        let swapped: Vec<u8> = data.chunks_exact(2).flat_map(|b| [b[1], b[0]]).collect();
        writer.write_image_data(&swapped).map_err(fail)?;
    } else {
        writer.write_image_data(data).map_err(fail)?;
    }
    writer.finish().map_err(fail)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_raw(path: &Path, w: u32, h: u32, c: png::ColorType, d: png::BitDepth, data: &[u8]) {
        let file = std::io::BufWriter::new(File::create(path).unwrap());
        let mut enc = png::Encoder::new(file, w, h);
        enc.set_color(c);
        enc.set_depth(d);
        enc.write_header().unwrap().write_image_data(data).unwrap();
    }

    #[test]
    fn grey_rgb_and_depth_decode_to_the_written_pixels() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (5u32, 3u32);
        let grey: Vec<u8> = (0..w * h).map(|i| (i * 17) as u8).collect();
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 + 1) as u8).collect();
        let depth: Vec<u16> = (0..w * h).map(|i| 300 + i as u16 * 1001).collect();
        let depth_be: Vec<u8> = depth.iter().flat_map(|v| v.to_be_bytes()).collect();
        let p = |n: &str| dir.path().join(n);
        write_raw(
            &p("g.png"),
            w,
            h,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &grey,
        );
        write_raw(
            &p("c.png"),
            w,
            h,
            png::ColorType::Rgb,
            png::BitDepth::Eight,
            &rgb,
        );
        write_raw(
            &p("d.png"),
            w,
            h,
            png::ColorType::Grayscale,
            png::BitDepth::Sixteen,
            &depth_be,
        );

        let g = PngImage::open(&p("g.png")).unwrap();
        assert_eq!((g.kind(), g.width(), g.height()), (StreamKind::Gray8, w, h));
        assert_eq!(g.decode().unwrap(), grey);
        let c = PngImage::open(&p("c.png")).unwrap();
        assert_eq!(c.kind(), StreamKind::Rgb8);
        assert_eq!(c.decode().unwrap(), rgb);
        let d = PngImage::open(&p("d.png")).unwrap();
        assert_eq!(d.kind(), StreamKind::Z16);
        let bytes = d.decode().unwrap();
        let back: Vec<u16> = bytes
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect();
        assert_eq!(back, depth);
    }

    #[test]
    fn alpha_garbage_and_wrong_buffers_are_refused_with_the_file_name() {
        let dir = tempfile::tempdir().unwrap();
        let rgba = dir.path().join("rgba.png");
        write_raw(
            &rgba,
            2,
            2,
            png::ColorType::Rgba,
            png::BitDepth::Eight,
            &[9; 16],
        );
        let e = PngImage::open(&rgba).unwrap_err().to_string();
        assert!(e.contains("rgba.png") && e.contains("alpha"), "{e}");

        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"not a png at all").unwrap();
        let e = PngImage::open(&junk).unwrap_err().to_string();
        assert!(
            e.contains("junk.png") && e.contains("not a readable PNG"),
            "{e}"
        );

        let e = PngImage::open(&dir.path().join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.png"), "{e}");

        let g = dir.path().join("g.png");
        write_raw(
            &g,
            2,
            2,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &[1, 2, 3, 4],
        );
        let mut small = [0u8; 3];
        let e = PngImage::open(&g)
            .unwrap()
            .decode_into(&mut small)
            .unwrap_err();
        assert!(e.to_string().contains("4 bytes"), "{e}");
    }

    #[test]
    fn written_frames_read_back_identical() {
        let dir = tempfile::tempdir().unwrap();
        for kind in StreamKind::ALL {
            let (w, h) = (7u32, 4u32);
            let n = FrameHeader::new(kind, w, h).payload_len();
            let data: Vec<u8> = (0..n).map(|i| (i * 37 + 11) as u8).collect();
            let p = dir.path().join(format!("{}.png", kind.name()));
            write(&p, kind, w, h, &data).unwrap();
            let img = PngImage::open(&p).unwrap();
            assert_eq!(img.kind(), kind);
            assert_eq!(img.decode().unwrap(), data, "{kind:?}");
        }
        let e = write(&dir.path().join("x.png"), StreamKind::Z16, 2, 2, &[0; 7]).unwrap_err();
        assert!(e.to_string().contains("needs 8 bytes"), "{e}");
    }

    #[test]
    fn a_truncated_png_is_an_error_not_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let g = dir.path().join("t.png");
        let data: Vec<u8> = (0..64 * 64).map(|i| (i * 31 % 251) as u8).collect();
        write_raw(
            &g,
            64,
            64,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &data,
        );
        let bytes = std::fs::read(&g).unwrap();
        std::fs::write(&g, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let result = PngImage::open(&g).and_then(|i| i.decode());
        assert!(result.is_err(), "a truncated PNG decoded");
    }
}
