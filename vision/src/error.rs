//! The crate's one error type.

use std::path::PathBuf;

/// Everything that can go wrong at the vision boundary. Each variant says which
/// file or which input was at fault and why; nothing here panics on bad input.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    /// The file could not be read at all (missing, a directory, no permission).
    #[error("{}: cannot read image file", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The bytes are not an image OpenCV can decode (empty, truncated, random bytes).
    #[error("{source_name}: not a decodable image ({reason})")]
    CorruptImage { source_name: String, reason: String },
    /// A 16-bit image (typically a depth PNG) where an 8-bit intensity image is needed.
    #[error("{source_name}: 16-bit image, expected 8-bit")]
    SixteenBit { source_name: String },
    /// Some other pixel format (float, signed, an odd channel count).
    #[error("{source_name}: unsupported pixel format: {what}")]
    UnsupportedImage { source_name: String, what: String },
    /// An image header claiming more pixels than anything here decodes.
    #[error(
        "{source_name}: the image header claims {width}x{height} pixels, more than the {max_pixels} \
         decoded at most (or zero): a corrupt or foreign file; refused before decoding"
    )]
    ImageTooLarge {
        source_name: String,
        width: u32,
        height: u32,
        max_pixels: u64,
    },
    /// An image whose size differs from the camera intrinsics' width and height.
    #[error(
        "{source_name}: the image is {width}x{height} but the camera intrinsics are for \
         {expected_width}x{expected_height}: images from another camera or resolution, or the \
         intrinsics of another stream?"
    )]
    ImageSizeMismatch {
        source_name: String,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    /// A zero-sized image or raw buffer whose length does not match its size.
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// The checkerboard description itself is unusable.
    #[error("invalid checkerboard spec: {0}")]
    InvalidSpec(String),
    /// Neither detector found a board of the requested size.
    #[error(
        "no {cols}x{rows} checkerboard (inner corners) found in the {width}x{height} image \
         (sharpness: variance of Laplacian {laplacian_var:.1})"
    )]
    BoardNotFound {
        cols: usize,
        rows: usize,
        width: u32,
        height: u32,
        laplacian_var: f64,
    },
    /// No board was found and the image is so smooth that it is most likely out of
    /// focus or motion-blurred.
    #[error(
        "no checkerboard found and the image looks blurred: variance of Laplacian \
         {laplacian_var:.1} < {threshold}"
    )]
    Blurred { laplacian_var: f64, threshold: f64 },
    /// Fewer corners than the spec or the pose solver needs.
    #[error("too few corners: {found}, need {needed}")]
    TooFewCorners { found: usize, needed: usize },
    /// The square colours do not fix which corner is the origin (a board that looks
    /// the same turned by 180°, inverted colours, or too little contrast).
    #[error("ambiguous board orientation: {0}")]
    AmbiguousOrientation(String),
    /// A detection given to the pose solver is inconsistent or the solver failed.
    #[error("board pose: {0}")]
    Pose(String),
    /// A marker dictionary name that is not one of OpenCV's predefined dictionaries.
    #[error(
        "unknown marker dictionary {0:?}: expected one of OpenCV's names, DICT_{{4X4,5X5,6X6,7X7}}_{{50,100,250,1000}}, \
         DICT_ARUCO_ORIGINAL or DICT_APRILTAG_{{16h5,25h9,36h10,36h11}}"
    )]
    UnknownDictionary(String),
    /// A ChArUco board, marker grid or marker description that is unusable (sizes,
    /// ids outside the dictionary).
    #[error("invalid target spec: {0}")]
    InvalidTarget(String),
    /// None of the markers the target needs was found in the image.
    #[error("no {what} found in the {width}x{height} image ({dictionary})")]
    MarkersNotFound {
        what: String,
        dictionary: &'static str,
        width: u32,
        height: u32,
    },
    /// The one marker asked for appears more than once, so its corners are ambiguous.
    #[error("marker {id} of {dictionary} appears {count} times in the image")]
    DuplicateMarker {
        id: usize,
        dictionary: &'static str,
        count: usize,
    },
    /// A multimarker file that cannot be used; `line` is 1-based (0: the whole file).
    #[error("{source_name}:{line}: {reason}")]
    MultimarkerFile {
        source_name: String,
        line: usize,
        reason: String,
    },
    /// Two poses explain the corners about equally well.
    #[error("ambiguous pose: {0}")]
    AmbiguousPose(String),
    /// Camera calibration could not run or gave an unusable result.
    #[error("intrinsics: {0}")]
    Intrinsics(String),
    /// Intrinsics asked for from a kind of target they are not calibrated from
    /// (only checkerboard and ChArUco images are).
    #[error(
        "intrinsics are calibrated from checkerboard or ChArUco images, not from a {kind} target"
    )]
    IntrinsicsTarget { kind: &'static str },
    /// A printable target could not be made or written.
    #[error("printable target: {0}")]
    Printable(String),
    /// OpenCV threw; `context` says which call.
    #[error("OpenCV {context}")]
    OpenCv {
        context: &'static str,
        #[source]
        source: opencv::Error,
    },
}

/// Attaches the name of the OpenCV call to an `opencv::Error`.
pub(crate) trait CvContext<T> {
    fn cv(self, context: &'static str) -> Result<T, VisionError>;
}

impl<T> CvContext<T> for opencv::Result<T> {
    fn cv(self, context: &'static str) -> Result<T, VisionError> {
        self.map_err(|source| VisionError::OpenCv { context, source })
    }
}

pub(crate) use b2b_errors::chain;

#[cfg(test)]
mod tests {
    use super::*;

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "missing for the test");
        assert_cause_once(&VisionError::Io {
            path: "/d/robot1/images/000.png".into(),
            source: io,
        });
        let source = opencv::Error::new(opencv::core::StsBadArg, "bad argument for the test");
        let e = VisionError::OpenCv {
            context: "findChessboardCornersSB",
            source,
        };
        assert_cause_once(&e);
        assert!(
            chain(&e).starts_with("OpenCV findChessboardCornersSB: "),
            "{e}"
        );
    }
}
