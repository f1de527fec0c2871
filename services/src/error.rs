//! The services library's one error type. Each variant says what went wrong
//! with the facts as fields (file, robot, frame, sizes); a variant that wraps
//! another error keeps it as its source and leaves it out of its own text, and
//! an error of another crate passed on as it is prints as it did
//! (`transparent`). The binaries print the chain once ([`crate::run_main`]).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use b2b_pipeline::PipelineError;

/// The services library's result.
pub type Result<T, E = ServiceError> = std::result::Result<T, E>;

/// What went wrong in the services' library.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    // The errors of the crates the services wire, passed on as they are.
    #[error(transparent)]
    Bus(#[from] b2b_bus::BusError),
    #[error(transparent)]
    Pipeline(Box<PipelineError>),
    #[error(transparent)]
    Store(Box<b2b_store::StoreError>),
    #[error(transparent)]
    Dataset(Box<b2b_dataset::DatasetError>),
    #[error(transparent)]
    Protocol(#[from] b2b_protocol::ProtocolError),
    #[error(transparent)]
    Calib(#[from] b2b_calib::CalibError),
    #[error(transparent)]
    Vision(#[from] b2b_vision::VisionError),
    #[error(transparent)]
    Robot(#[from] b2b_robot::RobotError),
    #[error(transparent)]
    Fri(Box<kuka_fri::FriError>),
    #[error(transparent)]
    Report(Box<b2b_report::ReportError>),
    #[error(transparent)]
    Watch(Box<b2b_watch::WatchError>),
    #[error(transparent)]
    Frames(#[from] b2b_frames::FramesError),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Live(#[from] b2b_live::LiveError),

    /// A file or folder that could not be read, written or created.
    #[error("cannot {action} {}", path.display())]
    Io {
        /// "read", "write", "create", "create state folder".
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A JSON file that is not the kind expected.
    #[error("{}: not a valid file of this kind", path.display())]
    NotValidFile {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    /// What a file holds is wrong (the cause says what).
    #[error("{}", path.display())]
    InFile {
        path: PathBuf,
        #[source]
        source: Box<ServiceError>,
    },

    // The agent and the coordinator on the bus.
    #[error("{}: not a sequence number", path.display())]
    NotASequenceNumber {
        path: PathBuf,
        #[source]
        source: std::num::ParseIntError,
    },
    /// A thread panicked holding one of the agent's locks.
    #[error("{what} lock poisoned")]
    Poisoned { what: &'static str },
    #[error("interrupted after {captures} captures")]
    InterruptedAfter { captures: u64 },
    /// The coordinator's solve failed; its reason as it sent it.
    #[error("the coordinator's solve failed: {reason}")]
    SolveFailed { reason: String },
    /// No result, and no coordinator ever announced a session.
    #[error(
        "no result from the coordinator within {waited_s} s, and no coordinator heard (a \
         running one announces its session twice a second): {why}"
    )]
    NoCoordinator {
        waited_s: u64,
        /// Why nobody may be hearing the agent ([`b2b_bus::Bus::unreached`]).
        why: String,
    },
    #[error("no result from the coordinator within {waited_s} s")]
    NoResult { waited_s: u64 },
    #[error("need two robots, heard from {}: {robots:?}", robots.len())]
    TooFewRobots { robots: Vec<String> },
    #[error(
        "the rgbd method pairs two robots' images, heard from {}: {robots:?} (give --robots a,b)",
        robots.len()
    )]
    RgbdNeedsTwoRobots { robots: Vec<String> },
    #[error("robots '{}', '{}': hand-eyes for the RGB-D method", robots[0], robots[1])]
    RgbdHandEyes {
        robots: [String; 2],
        #[source]
        source: Box<PipelineError>,
    },
    #[error("base-to-base needs two robots, the dataset lists {listed}")]
    DatasetNotTwoRobots { listed: usize },
    #[error("{}: format '{found}', expected '{expected}'", path.display())]
    WrongFormat {
        path: PathBuf,
        found: String,
        expected: &'static str,
    },
    #[error(
        "{}: robot '{robot}' is not in the dataset ({})",
        path.display(),
        robots.join(", ")
    )]
    HandEyeRobotNotInDataset {
        path: PathBuf,
        robot: String,
        robots: Vec<String>,
    },
    #[error("{}: a second hand-eye for robot '{robot}'", path.display())]
    SecondHandEye { path: PathBuf, robot: String },
    #[error("{}: covariance has a non-finite entry", path.display())]
    NonFiniteCovariance { path: PathBuf },
    #[error("--hand-eye: need one HANDEYE.json for each of {} and {}", robots[0], robots[1])]
    MissingHandEye { robots: [String; 2] },
    #[error("cannot read the history")]
    HistoryRead(#[source] Box<b2b_history::HistoryError>),
    #[error("cannot write the history to stdout")]
    HistoryWrite(#[source] std::io::Error),

    // The cell: its setup, the arm, the camera, the simulated cart.
    #[error("target")]
    SetupTarget(#[source] Box<PipelineError>),
    #[error("joint_margin_rad must be in [0, 0.5)")]
    JointMargin { value: f64 },
    #[error("speed_fraction must be in (0, 1]")]
    SpeedFraction { value: f64 },
    #[error("give a source: --sim SCENE or --fri HOST:PORT")]
    NoCart,
    #[error("--fri needs --setup FILE (arm model, target, approximate board and mount, workspace)")]
    FriNeedsSetup,
    #[error("--fri {addr}: not HOST:PORT")]
    FriAddress {
        addr: String,
        #[source]
        source: std::net::AddrParseError,
    },
    #[error("cannot start the FRI client on {bind}")]
    FriStart {
        bind: SocketAddr,
        #[source]
        source: Box<kuka_fri::FriError>,
    },
    #[error("cannot find this process's own executable")]
    OwnExecutable(#[source] std::io::Error),
    #[error(
        "the simulated cart's binary is not at {} (build it with `cargo build -p b2b-sim-cart`, or set B2B_SIM_CART)",
        path.display()
    )]
    NoCartBinary { path: PathBuf },
    #[error("cannot start the simulated cart {}", exe.display())]
    CartStart {
        exe: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The simulated cart refused to derive a setup; its stderr as it wrote it.
    #[error("the simulated cart refused {}: {stderr}", scene.display())]
    CartRefused { scene: PathBuf, stderr: String },
    #[error("the simulated cart's setup answer is not {{\"setup\": FILE}}: {stdout}")]
    CartAnswer {
        /// What the cart printed.
        stdout: String,
        #[source]
        source: serde_json::Error,
    },

    // The camera process (`camera`).
    #[error("--fps must be a number >= 0")]
    CameraFps { fps: f64 },
    #[error("no source: give --replay DIR or --realsense")]
    NoCameraSource,
    #[error(
        "this camera was built without RealSense support: install librealsense2 (see the README) and rebuild with `cargo build -p b2b-services --features realsense`"
    )]
    NoRealSenseSupport,
    #[error("cannot load {}", dir.display())]
    LoadDataset {
        dir: PathBuf,
        #[source]
        source: Box<b2b_dataset::DatasetError>,
    },
    #[error("{}: no robot {robot}", dir.display())]
    NoReplayRobot { dir: PathBuf, robot: String },
    #[error("robot {robot} is not in the dataset")]
    RobotNotInManifest { robot: String },
    #[error("{}: robot {robot} has no images to replay", dir.display())]
    NoImagesToReplay { dir: PathBuf, robot: String },
    #[error(
        "{}: robot {robot}: distortion has {count} coefficients; frames carry k1 k2 p1 p2 k3 only",
        manifest.display()
    )]
    TooManyDistortionCoefficients {
        manifest: PathBuf,
        robot: String,
        count: usize,
    },
    #[error(
        "{}: {}x{} image, but the manifest's camera is {}x{}",
        path.display(),
        size.0,
        size.1,
        manifest.0,
        manifest.1
    )]
    ImageNotManifestSize {
        path: PathBuf,
        size: (u32, u32),
        manifest: (u32, u32),
    },
    #[error("the dataset has depth images but no depth_unit_m")]
    NoDatasetDepthUnit,
    #[error("{}: a 16-bit image in the image column", path.display())]
    DepthInImageColumn { path: PathBuf },
    #[error(
        "{}: a depth image must be a 16-bit grey PNG, this is {}",
        path.display(),
        kind.name()
    )]
    DepthImageNotZ16 {
        path: PathBuf,
        kind: b2b_frames::StreamKind,
    },

    // Recordings.
    #[error("cannot write the recording {}", path.display())]
    RecordingSave {
        path: PathBuf,
        #[source]
        source: Box<b2b_viz::VizError>,
    },
    #[error("cannot stream to the rerun viewer at {addr}")]
    RecordingConnect {
        addr: String,
        #[source]
        source: Box<b2b_viz::VizError>,
    },

    /// Not a failure: the command ends with a documented exit status.
    #[error(transparent)]
    Exit(#[from] crate::ExitStatus),
}

impl ServiceError {
    /// The io error of `action` on `path`, for `map_err`.
    pub fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.to_owned();
        move |source| ServiceError::Io {
            action,
            path,
            source,
        }
    }

    /// This error as the cause of what is wrong in `path`.
    pub fn in_file(self, path: &Path) -> Self {
        ServiceError::InFile {
            path: path.to_owned(),
            source: Box::new(self),
        }
    }
}

/// `From` for the boxed errors, so that `?` boxes them.
macro_rules! boxed_from {
    ($($variant:ident: $error:ty),* $(,)?) => {
        $(
            impl From<$error> for ServiceError {
                fn from(e: $error) -> Self {
                    ServiceError::$variant(Box::new(e))
                }
            }
        )*
    };
}

boxed_from!(
    Pipeline: PipelineError,
    Store: b2b_store::StoreError,
    Dataset: b2b_dataset::DatasetError,
    Fri: kuka_fri::FriError,
    Report: b2b_report::ReportError,
    Watch: b2b_watch::WatchError,
);

#[cfg(test)]
mod tests {
    use super::*;

    fn io_error() -> std::io::Error {
        std::io::Error::new(std::io::ErrorKind::PermissionDenied, "denied")
    }

    /// Every variant that wraps a cause keeps it as its source and prints it
    /// once in the chain.
    #[test]
    fn wrapping_variants_keep_their_cause_once() {
        let json = || serde_json::from_str::<u8>("x").unwrap_err();
        let io = ServiceError::io("read", Path::new("a.json"))(io_error());
        for e in [
            ServiceError::io("create", Path::new("out"))(io_error()),
            ServiceError::NotValidFile {
                path: "a.json".into(),
                source: json(),
            },
            ServiceError::NotASequenceNumber {
                path: "a.seq".into(),
                source: "x".parse::<u64>().unwrap_err(),
            },
            ServiceError::HistoryWrite(io_error()),
            ServiceError::FriAddress {
                addr: "x".into(),
                source: "x".parse::<SocketAddr>().unwrap_err(),
            },
            ServiceError::OwnExecutable(io_error()),
            ServiceError::LoadDataset {
                dir: "/nonexistent".into(),
                source: Box::new(
                    b2b_dataset::Dataset::load(Path::new("/nonexistent")).unwrap_err(),
                ),
            },
            ServiceError::CartStart {
                exe: "cart".into(),
                source: io_error(),
            },
            ServiceError::CartAnswer {
                stdout: "?".into(),
                source: json(),
            },
            io.in_file(Path::new("setup.json")),
        ] {
            b2b_errors::assert_cause_once(&e);
        }
    }

    /// A message in a file reads "file: message: cause", as the same message
    /// with the file as its context did.
    #[test]
    fn a_file_names_itself_before_its_cause() {
        let e = ServiceError::from(b2b_live::LiveError::NoDepthUnit { frame: 3 })
            .in_file(Path::new("s.json"));
        assert_eq!(
            b2b_pipeline::error_chain(&e),
            "s.json: depth frame 3 has no depth unit"
        );
    }

    /// An exit status ends the command with its code whether the binary
    /// raised it or the library did; other errors carry none.
    #[test]
    fn an_exit_status_is_found_in_the_chain() {
        let status = || crate::ExitStatus {
            code: 3,
            message: "alarm".into(),
        };
        let own = status();
        assert_eq!(crate::exit_status(&own).map(|s| s.code), Some(3));
        let library = ServiceError::from(status());
        assert_eq!(crate::exit_status(&library).map(|s| s.code), Some(3));
        let wrapped = ServiceError::from(status()).in_file(Path::new("RESULT.json"));
        assert_eq!(crate::exit_status(&wrapped).map(|s| s.code), Some(3));
        assert!(crate::exit_status(&ServiceError::from(b2b_live::LiveError::NoPlan)).is_none());
    }

    /// Errors that pass through many functions stay small (clippy's
    /// `result_large_err` warns from 128 bytes).
    #[test]
    fn the_error_is_small() {
        assert!(std::mem::size_of::<ServiceError>() <= 128);
    }
}
