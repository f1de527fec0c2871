//! PNG writing with fixed settings, so that the same image always gives the same bytes.
//!
//! Compression level, filter and the absence of any time or text chunk are fixed; with
//! the `png` version pinned by `Cargo.lock`, a dataset regenerated from its scene and
//! seed is byte-identical to the committed one.

use std::io::BufWriter;
use std::path::Path;

use crate::SimError;
use crate::sensor::{DepthImage, GreyImage, RgbImage};

fn write(
    path: &Path,
    width: usize,
    height: usize,
    (colour, depth): (png::ColorType, png::BitDepth),
    bytes: &[u8],
) -> Result<(), SimError> {
    let png_err = |e: png::EncodingError| SimError::Png {
        file: path.to_owned(),
        message: e.to_string(),
    };
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| SimError::io(parent, e))?;
    }
    let file = std::fs::File::create(path).map_err(|e| SimError::io(path, e))?;
    let (w, h) = (
        u32::try_from(width).map_err(|_| SimError::invalid("image", "too wide"))?,
        u32::try_from(height).map_err(|_| SimError::invalid("image", "too high"))?,
    );
    let mut enc = png::Encoder::new(BufWriter::new(file), w, h);
    enc.set_color(colour);
    enc.set_depth(depth);
    enc.set_compression(png::Compression::Default);
    enc.set_filter(png::FilterType::Paeth);
    enc.set_adaptive_filter(png::AdaptiveFilterType::NonAdaptive);
    let mut writer = enc.write_header().map_err(png_err)?;
    writer.write_image_data(bytes).map_err(png_err)?;
    writer.finish().map_err(png_err)
}

/// Writes an 8-bit grey PNG.
pub fn write_grey(path: &Path, img: &GreyImage) -> Result<(), SimError> {
    let format = (png::ColorType::Grayscale, png::BitDepth::Eight);
    write(path, img.width, img.height, format, &img.data)
}

/// Writes an 8-bit RGB PNG.
pub fn write_rgb(path: &Path, img: &RgbImage) -> Result<(), SimError> {
    let format = (png::ColorType::Rgb, png::BitDepth::Eight);
    write(path, img.width, img.height, format, &img.data)
}

/// Writes a 16-bit grey PNG (big-endian, as PNG stores it) of depth units.
pub fn write_depth(path: &Path, img: &DepthImage) -> Result<(), SimError> {
    let bytes: Vec<u8> = img.data.iter().flat_map(|v| v.to_be_bytes()).collect();
    let format = (png::ColorType::Grayscale, png::BitDepth::Sixteen);
    write(path, img.width, img.height, format, &bytes)
}

/// Reads an 8-bit grey PNG (for tests and tools).
pub fn read_grey(path: &Path) -> Result<GreyImage, SimError> {
    let file = std::fs::File::open(path).map_err(|e| SimError::io(path, e))?;
    let png_err = |e: png::DecodingError| SimError::Png {
        file: path.to_owned(),
        message: e.to_string(),
    };
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(png_err)?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(png_err)?;
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Eight {
        return Err(SimError::Png {
            file: path.to_owned(),
            message: format!(
                "expected 8-bit grey, found {:?} {:?}",
                info.color_type, info.bit_depth
            ),
        });
    }
    buf.truncate(info.buffer_size());
    Ok(GreyImage {
        width: info.width as usize,
        height: info.height as usize,
        data: buf,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grey_round_trips_and_bytes_are_stable() {
        let dir = tempfile::tempdir().unwrap();
        let img = GreyImage {
            width: 7,
            height: 3,
            data: (0..21).map(|v| (v * 11) as u8).collect(),
        };
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        write_grey(&a, &img).unwrap();
        write_grey(&b, &img).unwrap();
        assert_eq!(read_grey(&a).unwrap(), img);
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }
}
