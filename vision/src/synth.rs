//! Rendering checkerboards with exactly known corner positions, for tests and benches.
//!
//! Each pixel is the mean of the board's reflectance over the pixel's square
//! footprint (a box filter, like an ideal sensor with 100 % fill factor), estimated
//! by supersampling. Under a box filter the image of a corner lies exactly at the
//! corner's projection, so a detector's output can be compared with
//! [`CameraModel::project`] of the known corner. Pixels whose footprint is a single
//! colour (checked on a 3x3 grid of points, and never near a square corner, where a
//! thin wedge could slip between the points) take that colour without supersampling.
//!
//! The board is rendered with the camera's distortion (rays are undistorted with
//! [`CameraModel::unproject`]), so it also serves distorted-camera tests.

use b2b_calib::camera::CameraModel;
use nalgebra::{Isometry3, Point2, Point3, Vector3};

use crate::checkerboard::CheckerboardSpec;
use crate::error::VisionError;
use crate::image::GrayImage;

/// What to render.
#[derive(Debug, Clone)]
pub struct BoardScene {
    pub spec: CheckerboardSpec,
    pub camera: CameraModel,
    /// `T_camera_target`. The printed side faces the camera when the camera is on
    /// the target's -z side.
    pub camera_from_target: Isometry3<f64>,
    /// Grey levels of the dark squares, the light squares and the white border, and
    /// of everything off the board.
    pub black: f64,
    pub white: f64,
    pub background: f64,
    /// Width of the white border around the outer squares, in squares.
    pub margin_squares: f64,
    /// Standard deviation of additive Gaussian noise, grey levels (0: none).
    pub noise_sigma: f64,
    pub seed: u64,
    /// Samples per pixel side where a pixel is supersampled.
    pub supersample: usize,
}

impl BoardScene {
    /// A scene with dark squares at 30, light at 220, background 120, a one-square
    /// white border, no noise and 16x16 supersampling.
    pub fn new(
        spec: CheckerboardSpec,
        camera: CameraModel,
        camera_from_target: Isometry3<f64>,
    ) -> Self {
        BoardScene {
            spec,
            camera,
            camera_from_target,
            black: 30.0,
            white: 220.0,
            background: 120.0,
            margin_squares: 1.0,
            noise_sigma: 0.0,
            seed: 1,
            supersample: 16,
        }
    }

    /// The true image position of every inner corner, by corner id; `None` if one
    /// is behind the camera.
    pub fn true_corners(&self) -> Option<Vec<Point2<f64>>> {
        (0..self.spec.corner_count())
            .map(|k| {
                self.camera
                    .project(&(self.camera_from_target * self.spec.target_point(k)))
            })
            .collect()
    }

    /// Reflectance at a point of the target plane.
    fn colour_at(&self, x: f64, y: f64) -> f64 {
        let s = self.spec.square_m;
        let (w, h) = (self.spec.cols as f64 * s, self.spec.rows as f64 * s);
        if x >= -s && x < w && y >= -s && y < h {
            let (a, b) = ((x / s).floor() as i64, (y / s).floor() as i64);
            // Outer-corner square (-1, -1) is black.
            if (a + b).rem_euclid(2) == 0 {
                self.black
            } else {
                self.white
            }
        } else {
            let m = s * (1.0 + self.margin_squares);
            if x >= -m && x < w + m - s && y >= -m && y < h + m - s {
                self.white
            } else {
                self.background
            }
        }
    }
}

/// Renders the scene; returns the image and the true corner positions by id.
pub fn render_checkerboard(
    scene: &BoardScene,
) -> Result<(GrayImage, Vec<Point2<f64>>), VisionError> {
    scene.spec.validate()?;
    let truth = scene
        .true_corners()
        .ok_or_else(|| VisionError::InvalidSpec("a board corner is behind the camera".into()))?;
    let cam = &scene.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    if w == 0 || h == 0 {
        return Err(VisionError::InvalidImage(
            "camera has a zero-sized image".into(),
        ));
    }
    let target_from_camera = scene.camera_from_target.inverse();
    let origin = target_from_camera.translation.vector;
    let undistorted = cam.dist.iter().all(|&d| d == 0.0);
    let shade = |u: f64, v: f64| -> f64 {
        let n = if undistorted {
            nalgebra::Vector2::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
        } else {
            cam.unproject(&Point2::new(u, v))
        };
        let d = target_from_camera.rotation * Vector3::new(n.x, n.y, 1.0);
        if d.z.abs() < 1e-12 {
            return scene.background;
        }
        let s = -origin.z / d.z;
        if s <= 0.0 {
            return scene.background;
        }
        scene.colour_at(origin.x + s * d.x, origin.y + s * d.y)
    };

    // Pixels near any square corner (inner, outer or border) are always supersampled.
    let mut special = vec![false; w * h];
    let sq = scene.spec.square_m;
    let m = sq * (1.0 + scene.margin_squares);
    let (bw, bh) = (scene.spec.cols as f64 * sq, scene.spec.rows as f64 * sq);
    let mut points: Vec<(f64, f64)> = Vec::new();
    for j in -1..=scene.spec.rows as i64 {
        for i in -1..=scene.spec.cols as i64 {
            points.push((i as f64 * sq, j as f64 * sq));
        }
    }
    points.extend([
        (-m, -m),
        (bw + m - sq, -m),
        (-m, bh + m - sq),
        (bw + m - sq, bh + m - sq),
    ]);
    for (x, y) in points {
        let Some(p) = cam.project(&(scene.camera_from_target * Point3::new(x, y, 0.0))) else {
            continue;
        };
        let (u0, v0) = (p.x.round() as i64, p.y.round() as i64);
        for v in v0 - 2..=v0 + 2 {
            for u in u0 - 2..=u0 + 2 {
                if u >= 0 && v >= 0 && (u as usize) < w && (v as usize) < h {
                    special[v as usize * w + u as usize] = true;
                }
            }
        }
    }

    let n = scene.supersample.max(1);
    let mut rng = Rng(scene.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let mut pixels = vec![0u8; w * h];
    for v in 0..h {
        for u in 0..w {
            let (uf, vf) = (u as f64, v as f64);
            let mut value = None;
            if !special[v * w + u] {
                let first = shade(uf, vf);
                let uniform = [-0.5, 0.0, 0.5].iter().all(|&dv| {
                    [-0.5, 0.0, 0.5]
                        .iter()
                        .all(|&du| shade(uf + du, vf + dv) == first)
                });
                if uniform {
                    value = Some(first);
                }
            }
            let mut value = value.unwrap_or_else(|| {
                let mut sum = 0.0;
                for sv in 0..n {
                    for su in 0..n {
                        let du = (su as f64 + 0.5) / n as f64 - 0.5;
                        let dv = (sv as f64 + 0.5) / n as f64 - 0.5;
                        sum += shade(uf + du, vf + dv);
                    }
                }
                sum / (n * n) as f64
            });
            if scene.noise_sigma > 0.0 {
                value += scene.noise_sigma * rng.gaussian();
            }
            pixels[v * w + u] = value.round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok((GrayImage::from_raw(w as u32, h as u32, &pixels)?, truth))
}

/// xorshift64* with Box–Muller: deterministic noise without a dependency.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
        ((x >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn gaussian(&mut self) -> f64 {
        let (a, b) = (self.next_f64(), self.next_f64());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

/// A flat textured surface for [`render_planes`]: an image lying in the plane z = 0 of
/// its own frame, printed side towards +z (seen only from the +z side), x right along
/// the image columns and y up against the rows. Texel `(col, row)` covers
/// x ∈ [x0 + col·texel, x0 + (col+1)·texel), y ∈ (y0 - (row+1)·texel, y0 - row·texel]
/// with `(x0, y0) = top_left_m`; outside the image the plane is transparent.
#[derive(Debug)]
pub struct TexturedPlane {
    pub texture: GrayImage,
    /// `T_target_plane`.
    pub target_from_plane: Isometry3<f64>,
    pub top_left_m: Point2<f64>,
    pub texel_m: f64,
}

impl TexturedPlane {
    /// The faces of a multimarker set drawn by [`crate::multimarker::render_face`]
    /// with `margin_m` of white around the markers, at `px_per_m`.
    pub fn multimarker_faces(
        config: &crate::multimarker::MultimarkerConfig,
        dictionary: &crate::markers::MarkerDictionary,
        px_per_m: f64,
        margin_m: f64,
    ) -> Result<Vec<TexturedPlane>, VisionError> {
        config
            .faces()
            .iter()
            .map(|face| {
                let (texture, top_left_m) =
                    crate::multimarker::render_face(face, dictionary, px_per_m, margin_m)?;
                Ok(TexturedPlane {
                    texture,
                    target_from_plane: face.set_from_face,
                    top_left_m,
                    texel_m: 1.0 / px_per_m,
                })
            })
            .collect()
    }
}

/// A scene of textured planes for [`render_planes`].
#[derive(Debug)]
pub struct PlaneScene {
    pub camera: CameraModel,
    /// `T_camera_target`.
    pub camera_from_target: Isometry3<f64>,
    pub planes: Vec<TexturedPlane>,
    /// Grey level where no plane is seen.
    pub background: f64,
    /// Standard deviation of additive Gaussian noise, grey levels (0: none).
    pub noise_sigma: f64,
    pub seed: u64,
    /// Samples per pixel side where a pixel is not uniform.
    pub supersample: usize,
}

/// Renders textured planes by ray casting (the nearest plane hit wins, so faces
/// hide each other), box-filtered like [`render_checkerboard`]: a pixel whose four
/// corners and centre see the same texel value is that value, any other pixel is the
/// mean of `supersample²` samples. With texel edges at known plane positions the image
/// of an edge or corner is exactly its projection (up to the sampling).
pub fn render_planes(scene: &PlaneScene) -> Result<GrayImage, VisionError> {
    let cam = &scene.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    if w == 0 || h == 0 {
        return Err(VisionError::InvalidImage(
            "camera has a zero-sized image".into(),
        ));
    }
    for p in &scene.planes {
        if !(p.texel_m.is_finite() && p.texel_m > 0.0) {
            return Err(VisionError::InvalidSpec(format!(
                "texel size {} m must be positive and finite",
                p.texel_m
            )));
        }
    }
    // Each plane in the camera frame: origin, axes, normal.
    let planes: Vec<(Isometry3<f64>, &TexturedPlane)> = scene
        .planes
        .iter()
        .map(|p| {
            (
                (scene.camera_from_target * p.target_from_plane).inverse(),
                p,
            )
        })
        .collect();
    let undistorted = cam.dist.iter().all(|&d| d == 0.0);
    let shade = |u: f64, v: f64| -> f64 {
        let n = if undistorted {
            nalgebra::Vector2::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
        } else {
            cam.unproject(&Point2::new(u, v))
        };
        let ray = Vector3::new(n.x, n.y, 1.0);
        let mut best = (f64::INFINITY, scene.background);
        for (plane_from_camera, p) in &planes {
            let o = plane_from_camera.translation.vector;
            // Seen only from the printed (+z) side.
            if o.z <= 0.0 {
                continue;
            }
            let d = plane_from_camera.rotation * ray;
            if d.z >= -1e-12 {
                continue;
            }
            let s = -o.z / d.z;
            if s <= 0.0 || s >= best.0 {
                continue;
            }
            let (x, y) = (o.x + s * d.x, o.y + s * d.y);
            let col = ((x - p.top_left_m.x) / p.texel_m).floor();
            let row = ((p.top_left_m.y - y) / p.texel_m).floor();
            let (tw, th) = (p.texture.width() as f64, p.texture.height() as f64);
            if col >= 0.0 && row >= 0.0 && col < tw && row < th {
                let value = p.texture.pixels()[row as usize * tw as usize + col as usize];
                best = (s, f64::from(value));
            }
        }
        best.1
    };
    // Shade at pixel corners, shared between neighbours.
    let mut corners = vec![0.0; (w + 1) * (h + 1)];
    for v in 0..=h {
        for u in 0..=w {
            corners[v * (w + 1) + u] = shade(u as f64 - 0.5, v as f64 - 0.5);
        }
    }
    let n = scene.supersample.max(1);
    let mut rng = Rng(scene.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let mut pixels = vec![0u8; w * h];
    for v in 0..h {
        for u in 0..w {
            let (uf, vf) = (u as f64, v as f64);
            let c = [
                corners[v * (w + 1) + u],
                corners[v * (w + 1) + u + 1],
                corners[(v + 1) * (w + 1) + u],
                corners[(v + 1) * (w + 1) + u + 1],
            ];
            let centre = shade(uf, vf);
            let mut value = if c.iter().all(|&x| x == centre) {
                centre
            } else {
                let mut sum = 0.0;
                for sv in 0..n {
                    for su in 0..n {
                        let du = (su as f64 + 0.5) / n as f64 - 0.5;
                        let dv = (sv as f64 + 0.5) / n as f64 - 0.5;
                        sum += shade(uf + du, vf + dv);
                    }
                }
                sum / (n * n) as f64
            };
            if scene.noise_sigma > 0.0 {
                value += scene.noise_sigma * rng.gaussian();
            }
            pixels[v * w + u] = value.round().clamp(0.0, 255.0) as u8;
        }
    }
    GrayImage::from_raw(w as u32, h as u32, &pixels)
}
