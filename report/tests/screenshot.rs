//! Renders reports in headless Chromium and checks the screenshots are real
//! pages: the right size, not blank, with the plots drawn (pixels of the robots'
//! plot colours in both columns of the grid), and that a report without the
//! per-capture data really has fewer plots (so the check can fail).
//!
//! Needs `/usr/bin/chromium` (apt package `chromium`). Set
//! `B2B_SKIP_BROWSER_TESTS=1` to skip on a machine without it; otherwise a
//! missing browser fails the test.
//!
//! `B2B_REPORT_SCREENSHOT=path.png` keeps a half-size copy of the full report's
//! screenshot (how `report/docs/screenshot.png` was made).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use b2b_report::{CaptureDetail, ReportInputs, TouchDetail, write_report};

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 2000;
const CHROMIUM: &str = "/usr/bin/chromium";

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// RESULT.json and VERIFY.json from a replay of the simulator's two-robot
/// dataset, plus per-capture details and per-touch errors as the coordinator
/// would add them.
fn full_inputs() -> ReportInputs {
    let mut inputs =
        ReportInputs::from_files(&fixture("RESULT.json"), Some(&fixture("VERIFY.json"))).unwrap();
    for (r, robot) in ["robot1", "robot2"].iter().enumerate() {
        for i in 0..14u64 {
            let rejected = (r == 0 && i == 13) || (r == 1 && i == 12);
            let tilt = (10.0 + 4.0 * i as f64 + 3.0 * r as f64).to_radians();
            let az = (i as f64 * 137.5 + 40.0 * r as f64).to_radians();
            // Cameras on the -z side of the board (OpenCV target frame).
            let dir = [tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos()];
            inputs.captures.push(CaptureDetail {
                robot: robot.to_string(),
                index: i,
                label: Some(format!("images/{i:03}.png")),
                rms_px: (!rejected).then(|| {
                    0.12 + 0.03 * ((i as f64) * 1.3 + r as f64).sin().abs() + 0.02 * r as f64
                }),
                outlier_corners: Some((i % 3) as usize),
                view_direction: Some(dir),
                rejected: rejected.then(|| "board not found".to_owned()),
            });
        }
    }
    for row in 1..=25 {
        // Like the fixture's verify report: mean about 0.7 mm, one touch of 25
        // over its bound.
        let error_m = if row == 17 {
            1.44e-3
        } else {
            1e-4 * (3.0 + 7.0 * ((row as f64) * 0.77).sin().abs())
        };
        inputs.touches.push(TouchDetail {
            row,
            error_m,
            bound95_m: 1.05e-3 + 1e-5 * row as f64,
        });
    }
    inputs
}

/// Runs headless Chromium on a page, returning the PNG path.
fn screenshot(page: &Path, dir: &Path) -> PathBuf {
    let png = dir.join("shot.png");
    let profile = tempfile::tempdir().unwrap();
    let mut child = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(format!("--window-size={WIDTH},{HEIGHT}"))
        .arg(format!("--screenshot={}", png.display()))
        .arg(format!("file://{}", page.display()))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {CHROMIUM}: {e}"));
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "chromium exited with {status}");
            break;
        }
        if Instant::now() > deadline {
            child.kill().ok();
            child.wait().ok();
            panic!("chromium did not finish in 90 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(png.exists(), "chromium wrote no screenshot");
    png
}

struct Rgb {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl Rgb {
    fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Pixels within `tol` of `colour` in the rectangle.
    fn count_near(&self, colour: [u8; 3], tol: i32, x0: u32, x1: u32, y0: u32, y1: u32) -> usize {
        let mut n = 0;
        for y in y0..y1.min(self.height) {
            for x in x0..x1.min(self.width) {
                let p = self.pixel(x, y);
                if (0..3).all(|c| (p[c] as i32 - colour[c] as i32).abs() <= tol) {
                    n += 1;
                }
            }
        }
        n
    }

    fn non_background(&self) -> f64 {
        let mut n = 0;
        for y in 0..self.height {
            for x in 0..self.width {
                let p = self.pixel(x, y);
                if p.iter().any(|&c| c < 200) {
                    n += 1;
                }
            }
        }
        n as f64 / (self.width * self.height) as f64
    }
}

fn decode(path: &Path) -> Rgb {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => panic!("unexpected PNG colour type {other:?}"),
    };
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let data = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    Rgb {
        width: info.width,
        height: info.height,
        data,
    }
}

/// Writes the image at half its size (2x2 box filter), for the docs.
fn save_half_size(img: &Rgb, path: &Path) {
    let (w, h) = (img.width / 2, img.height / 2);
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let sum: u32 = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|(dx, dy)| u32::from(img.pixel(2 * x + dx, 2 * y + dy)[c]))
                    .sum();
                data.push(((sum + 2) / 4) as u8);
            }
        }
    }
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, w, h);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Best);
    encoder
        .write_header()
        .unwrap()
        .write_image_data(&data)
        .unwrap();
}

const BLUE: [u8; 3] = [0x00, 0x72, 0xB2];
const ORANGE: [u8; 3] = [0xE6, 0x9F, 0x00];

fn skip() -> bool {
    if std::env::var_os("B2B_SKIP_BROWSER_TESTS").is_some() {
        eprintln!("B2B_SKIP_BROWSER_TESTS set: not running Chromium");
        return true;
    }
    assert!(
        Path::new(CHROMIUM).exists(),
        "{CHROMIUM} is missing: apt-get install chromium (scripts/setup), \
         or set B2B_SKIP_BROWSER_TESTS=1"
    );
    false
}

#[test]
fn the_full_report_renders_as_a_real_page_with_its_plots() {
    if skip() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let files = write_report(&full_inputs(), &dir.path().join("report")).unwrap();
    assert_eq!(files.plots.len(), 6, "{:?}", files.plots);
    let png = screenshot(&files.index, dir.path());
    let img = decode(&png);
    if let Some(keep) = std::env::var_os("B2B_REPORT_SCREENSHOT") {
        save_half_size(&img, Path::new(&keep));
    }
    assert_eq!((img.width, img.height), (WIDTH, HEIGHT));
    let ink = img.non_background();
    eprintln!("full: ink {ink:.4}");
    assert!(
        ink > 0.03,
        "page looks blank: {:.3} of pixels are not white",
        ink
    );
    // The plots sit in a two-column grid below the cards and the numbers; both
    // robots' colours must show up in both columns (dots, bars, legend swatches).
    let mid = WIDTH / 2;
    for (colour, name) in [(BLUE, "robot1 blue"), (ORANGE, "robot2 orange")] {
        let left = img.count_near(colour, 40, 0, mid, 300, HEIGHT);
        let right = img.count_near(colour, 40, mid, WIDTH, 300, HEIGHT);
        eprintln!("{name}: {left} px left, {right} px right");
        assert!(
            left > 300 && right > 300,
            "{name}: {left} px left, {right} px right"
        );
    }
    // Touches over their bound and rejected captures are drawn in red.
    let red = img.count_near([0xC0, 0x39, 0x2B], 30, 0, WIDTH, 0, HEIGHT);
    assert!(red > 50, "no red marks ({red} px)");
}

#[test]
fn a_result_only_report_renders_and_has_no_capture_plots() {
    if skip() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut inputs = ReportInputs::from_files(&fixture("RESULT.json"), None).unwrap();
    inputs.result.captures.rejected.clear();
    let files = write_report(&inputs, &dir.path().join("report")).unwrap();
    assert!(files.plots.is_empty(), "{:?}", files.plots);
    let img = decode(&screenshot(&files.index, dir.path()));
    assert_eq!((img.width, img.height), (WIDTH, HEIGHT));
    // Text and tables but no plot colours: the full report's check above would fail here.
    assert!(img.non_background() > 0.002, "no text at all");
    let blue = img.count_near(BLUE, 40, 0, WIDTH, 300, HEIGHT);
    eprintln!(
        "result only: {blue} blue px, ink {:.4}",
        img.non_background()
    );
    if let Some(keep) = std::env::var_os("B2B_REPORT_SCREENSHOT_RESULT_ONLY") {
        save_half_size(&img, Path::new(&keep));
    }
    assert!(blue < 300, "{blue} blue px in a report without plots");
}
