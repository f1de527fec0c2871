//! `b2b-vision-tool`: printable calibration targets and camera intrinsics.
//!
//! - `target --target JSON --out DIR [--dpi N] [--margin-mm M]`: writes the target as
//!   SVG (exact physical size) and PNG (at N DPI), plus the multimarker file for a
//!   multimarker target. `JSON` is a dataset `target` block (shared/dataset-format.md)
//!   or a whole `dataset.json`; a multimarker `config` is read relative to the JSON's
//!   folder. `--builtin multimarker-4x3|multimarker-corner|marker` prints a built-in
//!   layout instead (`--dictionary`, and `--id`/`--marker-mm` for a single marker).
//! - `intrinsics --images DIR --target JSON --out CAMERA.json`: calibrates a camera
//!   from checkerboard or ChArUco images and writes the `camera` block of
//!   `dataset.json`; prints each image's error or why it was rejected.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use b2b_services::{init_logging, run_main, write_json};
use b2b_vision::intrinsics::{IntrinsicsOptions, calibrate_intrinsics_from_dir};
use b2b_vision::multimarker::MultimarkerConfig;
use b2b_vision::printable::{marker_page, write_pages, write_printable};
use b2b_vision::{MarkerDictionary, Target};
use clap::{Parser, Subcommand, ValueEnum};

#[derive(Parser, Debug)]
#[command(
    name = "b2b-vision-tool",
    version,
    about = "Printable calibration targets and camera intrinsics"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Builtin {
    /// ARToolKit5's multi-barcode-4x3 sheet (12 markers, 40 mm).
    Multimarker4x3,
    /// The three-face corner (floor and two walls, 2x2 markers of 40 mm each).
    MultimarkerCorner,
    /// One marker (`--id`, `--marker-mm`).
    Marker,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Write a target as SVG (exact size in mm) and PNG (at --dpi), plus the
    /// multimarker file for a multimarker target.
    Target(TargetArgs),
    /// Calibrate a camera from board images and write dataset.json's camera block.
    Intrinsics(IntrinsicsArgs),
}

// The flags of `target` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct TargetArgs {
    /// A dataset `target` block or a whole dataset.json.
    #[arg(long, conflicts_with = "builtin", required_unless_present = "builtin")]
    target: Option<PathBuf>,
    /// A built-in layout instead of --target.
    #[arg(long, value_enum)]
    builtin: Option<Builtin>,
    /// Dictionary of a built-in layout (OpenCV name).
    #[arg(long, default_value = "DICT_4X4_50")]
    dictionary: String,
    /// Marker id of `--builtin marker`.
    #[arg(long, default_value_t = 0)]
    id: usize,
    /// Marker width of `--builtin marker`, millimetres.
    #[arg(long, default_value_t = 100.0)]
    marker_mm: f64,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// File name stem.
    #[arg(long, default_value = "target")]
    stem: String,
    /// PNG resolution.
    #[arg(long, default_value_t = 300.0)]
    dpi: f64,
    /// White margin around the target, millimetres (at least one marker cell for
    /// marker targets).
    #[arg(long, default_value_t = 15.0)]
    margin_mm: f64,
}

// The flags of `intrinsics` (the help is the variant's doc comment).
#[derive(clap::Args, Debug)]
struct IntrinsicsArgs {
    /// Folder of images (png, jpg, bmp, tif).
    #[arg(long)]
    images: PathBuf,
    /// The board: a checkerboard or charuco `target` block, or a dataset.json.
    #[arg(long)]
    target: PathBuf,
    /// Where to write the camera block (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Fit k3 as well (default: k3 = 0).
    #[arg(long)]
    fit_k3: bool,
}

/// Reads a target block, or the `target` of a dataset.json.
fn read_block(path: &Path) -> anyhow::Result<b2b_dataset::Target> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not valid JSON", path.display()))?;
    let block = value.get("target").cloned().unwrap_or(value);
    serde_json::from_value(block).with_context(|| {
        format!(
            "{}: not a target block (kind checkerboard, charuco, aruco_grid or multimarker)",
            path.display()
        )
    })
}

/// The target a `--target` file describes, read as a dataset's is (a multimarker
/// `config` relative to the file's folder).
fn target_of(json: &Path) -> anyhow::Result<Target> {
    Ok(b2b_pipeline::target_from_manifest(
        &read_block(json)?,
        json,
    )?)
}

/// `target`: a printable target.
fn target(args: TargetArgs) -> anyhow::Result<()> {
    let TargetArgs {
        target,
        builtin,
        dictionary,
        id,
        marker_mm,
        out,
        stem,
        dpi,
        margin_mm,
    } = args;
    let margin = margin_mm * 1e-3;
    let files = match (target, builtin) {
        (Some(json), _) => write_printable(&target_of(&json)?, dpi, margin, &out, &stem)?,
        (None, Some(Builtin::Multimarker4x3)) => {
            let target = Target::Multimarker {
                config: MultimarkerConfig::grid_4x3(),
                dictionary: MarkerDictionary::parse(&dictionary)?,
            };
            write_printable(&target, dpi, margin, &out, &stem)?
        }
        (None, Some(Builtin::MultimarkerCorner)) => {
            let target = Target::Multimarker {
                config: MultimarkerConfig::three_face_corner(),
                dictionary: MarkerDictionary::parse(&dictionary)?,
            };
            write_printable(&target, dpi, margin, &out, &stem)?
        }
        (None, Some(Builtin::Marker)) => {
            let page = marker_page(&dictionary, id, marker_mm * 1e-3, margin)?;
            write_pages(&[page], dpi, &out, &stem)?
        }
        (None, None) => bail!("give --target JSON or --builtin"),
    };
    for f in files {
        println!("{}", f.display());
    }
    Ok(())
}

/// `intrinsics`: a camera's intrinsics from board images.
fn intrinsics(args: IntrinsicsArgs) -> anyhow::Result<()> {
    let IntrinsicsArgs {
        images,
        target,
        out,
        fit_k3,
    } = args;
    let board = target_of(&target)?;
    let options = IntrinsicsOptions {
        fit_k3,
        ..Default::default()
    };
    let r = calibrate_intrinsics_from_dir(&images, &board, &options)?;
    for i in &r.images {
        match (&i.rejected, i.rms_px) {
            (None, Some(e)) => println!("{}: {} corners, {e:.3} px", i.name, i.corners),
            (Some(why), _) => println!("{}: rejected: {why}", i.name),
            (None, None) => println!("{}: used", i.name),
        }
    }
    let c = &r.camera;
    println!(
        "{} of {} images, RMS {:.3} px: fx {:.2} fy {:.2} cx {:.2} cy {:.2} dist {:?}",
        r.used(),
        r.images.len(),
        r.rms_px,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        r.dist5()
    );
    write_json(&out, &b2b_dataset::intrinsics_of(&r.camera, 5))?;
    Ok(())
}

fn main() -> std::process::ExitCode {
    init_logging();
    let cli = Cli::parse();
    run_main::<anyhow::Error>(|| match cli.command {
        Command::Target(args) => target(args),
        Command::Intrinsics(args) => intrinsics(args),
    })
}

b2b_services::every_flag_has_help!(Cli);
