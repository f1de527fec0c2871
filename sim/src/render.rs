//! The physical camera: ray casting through OpenCV's distortion model, adaptive
//! supersampling, thin-lens defocus, illumination and vignetting.
//!
//! The output is *irradiance in digital numbers* (before sensor noise and quantisation,
//! see [`crate::sensor`]) and the true z-depth of every pixel centre.
//!
//! Physics choices, and why:
//!
//! - **Exact geometry through the real lens model.** A pixel is a unit square on the
//!   sensor (OpenCV convention: pixel `(u, v)` is centred on integer coordinates). Its
//!   corners are undistorted by Newton's method on the OpenCV model (`k1, k2, p1, p2,
//!   k3[, k4..k6]`) — exactly the inverse of `CameraModel::project` — giving one ray per
//!   corner; every ray is intersected exactly with the scene's planar quads. No
//!   rasterisation, no bitmap resampling: a corner of the board lands where projecting
//!   it with the camera model puts it. Rays inside a pixel are bilinear interpolations
//!   of its corner rays (the lens map is smooth: the error is below 1e-4 px even at the
//!   image corners of a strongly distorted lens).
//! - **Box-filter pixel integration by adaptive supersampling.** A pixel whose four
//!   corner rays hit the same convex texture region of the same convex quad is uniform,
//!   so one sample is exact (see [`crate::texture`]). Other pixels (edges, corners of
//!   squares, silhouettes, and pixels holding a quad's vertex) are averaged over
//!   `edge_samples` points of a Fibonacci lattice (stratified along both axes, so edges
//!   at every angle are resolved to ~1/`edge_samples` of a pixel); continuously
//!   varying textures over `varying_samples`. This is the pixel's area integral (100 % fill factor), the
//!   anti-aliasing a real sensor does, at a cost proportional to the edge length.
//! - **Illumination.** A light of `lux` illuminance on a surface facing it, with an
//!   ambient fraction and a linear gradient across the scene (one side of the table
//!   brighter than the other), Lambertian in the angle between the visible face's
//!   normal and the light. Surfaces are diffuse (paper, toner, cardboard): no specular
//!   highlights.
//! - **Defocus.** A thin lens focused at `focus_m` with aperture diameter `aperture_m`
//!   images a point at depth `z` as a disc of diameter `c = fx · D · |1/z − 1/z_f|`
//!   pixels. The disc is approximated by the Gaussian of equal second moment
//!   (`σ = c/4`), combined in quadrature with the lens's own point-spread function
//!   `psf_sigma_px`; σ varies per pixel with its depth. A symmetric blur does not move
//!   edges, so it costs contrast, not accuracy, exactly as in a real camera.
//! - **Vignetting.** Natural `cos⁴θ` fall-off of irradiance with the angle θ from the
//!   optical axis, scaled by `vignetting` (0 = none, 1 = the full cos⁴ law; real lenses
//!   compensate part of it).

use std::sync::Arc;

use b2b_calib::camera::CameraModel;
use nalgebra::{Point3, Translation3, UnitQuaternion, Vector3};

use crate::texture::{Checkerboard, TexSample, Texture, VARYING};
use crate::{Iso3, SimError};

/// A planar rectangle `[min, max]` in the `x, y` plane of its own frame, carrying a
/// texture in those coordinates. Quads are visible from both sides.
#[derive(Debug, Clone)]
pub struct Quad {
    pub world_from_quad: Iso3,
    pub min: [f64; 2],
    pub max: [f64; 2],
    pub texture: Arc<dyn Texture>,
}

/// Everything a camera can see: planar quads (boards, table, box faces, occluders).
#[derive(Debug, Clone, Default)]
pub struct SceneGeometry {
    pub quads: Vec<Quad>,
}

impl SceneGeometry {
    /// Adds a quad.
    pub fn add_quad(
        &mut self,
        world_from_quad: Iso3,
        min: [f64; 2],
        max: [f64; 2],
        texture: Arc<dyn Texture>,
    ) {
        self.quads.push(Quad {
            world_from_quad,
            min,
            max,
            texture,
        });
    }

    /// Adds a printed checkerboard whose target frame is `world_from_target`.
    pub fn add_checkerboard(&mut self, world_from_target: Iso3, board: Checkerboard) {
        let (min, max) = board.extent();
        self.add_quad(world_from_target, min, max, Arc::new(board));
    }

    /// Adds a box of full `size` centred on `world_from_box`'s origin; face `k` (in the
    /// order +x, −x, +y, −y, +z, −z) carries `textures[k]`, in metres from the face centre.
    pub fn add_box(
        &mut self,
        world_from_box: Iso3,
        size: [f64; 3],
        textures: [Arc<dyn Texture>; 6],
    ) {
        use std::f64::consts::FRAC_PI_2;
        let rotations = [
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), FRAC_PI_2),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -FRAC_PI_2),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -FRAC_PI_2),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2),
            UnitQuaternion::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        ];
        let half = Vector3::new(size[0], size[1], size[2]) / 2.0;
        for (rot, texture) in rotations.into_iter().zip(textures) {
            let extent = |axis: Vector3<f64>| {
                let a = rot * axis;
                a.x.abs() * half.x + a.y.abs() * half.y + a.z.abs() * half.z
            };
            let (hx, hy, hz) = (
                extent(Vector3::x()),
                extent(Vector3::y()),
                extent(Vector3::z()),
            );
            let box_from_face = Iso3::from_parts(Translation3::from(rot * Vector3::z() * hz), rot);
            self.add_quad(
                world_from_box * box_from_face,
                [-hx, -hy],
                [hx, hy],
                texture,
            );
        }
    }
}

/// The light.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lighting {
    /// Illuminance on a surface facing the light, lux (the seed experiment used 145, 243
    /// and 352 lx).
    pub lux: f64,
    /// Fraction of the light that is diffuse (reaches every surface regardless of its
    /// orientation).
    #[serde(default = "default_ambient")]
    pub ambient: f64,
    /// Direction from the scene towards the light, in the world frame.
    #[serde(default = "default_light_dir")]
    pub towards_light: [f64; 3],
    /// Relative change of illuminance per metre, in the world frame.
    #[serde(default)]
    pub gradient_per_m: [f64; 3],
    /// Where the gradient is zero, in the world frame.
    #[serde(default)]
    pub gradient_origin: [f64; 3],
}

fn default_ambient() -> f64 {
    0.4
}

fn default_light_dir() -> [f64; 3] {
    [0.2, 0.1, 1.0]
}

impl Lighting {
    /// A room light of `lux` from above, no gradient.
    pub fn uniform(lux: f64) -> Self {
        Lighting {
            lux,
            ambient: 1.0,
            towards_light: [0.0, 0.0, 1.0],
            gradient_per_m: [0.0; 3],
            gradient_origin: [0.0; 3],
        }
    }
}

/// The lens beyond its geometric model.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Optics {
    /// Aperture diameter, m (focal length / f-number). 0 = pinhole (no defocus).
    #[serde(default)]
    pub aperture_m: f64,
    /// Distance in focus, m.
    #[serde(default = "default_focus")]
    pub focus_m: f64,
    /// The lens's own blur (and the sensor's), Gaussian σ in pixels.
    #[serde(default)]
    pub psf_sigma_px: f64,
    /// Strength of cos⁴ vignetting, 0..=1.
    #[serde(default)]
    pub vignetting: f64,
}

fn default_focus() -> f64 {
    0.5
}

impl Optics {
    /// A perfect pinhole: no blur, no vignetting.
    pub fn ideal() -> Self {
        Optics {
            aperture_m: 0.0,
            focus_m: 0.5,
            psf_sigma_px: 0.0,
            vignetting: 0.0,
        }
    }

    /// A RealSense D4xx colour camera: ~1.9 mm f/2 lens (0.95 mm aperture) at fixed
    /// focus, a mild PSF and partly compensated vignetting.
    pub fn realsense() -> Self {
        Optics {
            aperture_m: 0.95e-3,
            focus_m: 0.5,
            psf_sigma_px: 0.35,
            vignetting: 0.4,
        }
    }
}

/// How to render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// Samples in pixels that straddle an edge (rounded up to a Fibonacci number).
    pub edge_samples: usize,
    /// Samples in pixels of a continuously varying texture (likewise).
    pub varying_samples: usize,
    pub lighting: Lighting,
    pub optics: Optics,
    /// Exposure: digital numbers for a perfect white reflector per lux (fixed exposure
    /// time and gain, as with auto-exposure off).
    pub dn_per_lux: f64,
    /// Where rays hit nothing, DN.
    pub background_dn: f64,
    /// Also render the three colour channels ([`Irradiance::rgb`]).
    pub colour: bool,
}

impl RenderSettings {
    /// Exact geometry only: uniform light, no blur, no vignetting; white paper at
    /// 352 lx is ~235 DN.
    pub fn ideal() -> Self {
        RenderSettings {
            edge_samples: 377,
            varying_samples: 13,
            lighting: Lighting::uniform(352.0),
            optics: Optics::ideal(),
            dn_per_lux: DN_PER_LUX,
            background_dn: 20.0,
            colour: false,
        }
    }
}

/// Default exposure: white paper (reflectance 0.85) at 352 lx gives 235 DN.
pub const DN_PER_LUX: f64 = 235.0 / (0.85 * 352.0);

/// Irradiance image (DN, before noise and quantisation) and true depth.
#[derive(Debug, Clone, PartialEq)]
pub struct Irradiance {
    pub width: usize,
    pub height: usize,
    /// Row-major, DN.
    pub dn: Vec<f32>,
    /// True z-depth of each pixel centre's ray, m; 0 where the ray hits nothing.
    pub depth_m: Vec<f32>,
    /// Red, green, blue DN per pixel when rendered in colour, else empty. Prints are
    /// tinted with luminance `0.299 r + 0.587 g + 0.114 b = 1`, so `dn` is the
    /// luminance of these channels (up to the clipping of saturated tints).
    pub rgb: Vec<[f32; 3]>,
}

/// OpenCV's distortion of normalised coordinates and its Jacobian (row-major 2x2):
/// the camera model's own formula, so renderer and solver agree by construction.
fn distort(d: &[f64; 8], x: f64, y: f64) -> (f64, f64, [f64; 4]) {
    let (xd, yd, j, _) = b2b_calib::camera::distort_normalised(d, x, y);
    (xd, yd, [j[0][0], j[0][1], j[1][0], j[1][1]])
}

/// Normalised coordinates of pixel `(u, v)` by Newton's method from `guess`; `None`
/// where the distortion model folds over (no unique inverse) or does not converge.
fn undistort(cam: &CameraModel, u: f64, v: f64, guess: [f64; 2]) -> Option<[f64; 2]> {
    let xd = (u - cam.cx) / cam.fx;
    let yd = (v - cam.cy) / cam.fy;
    let [mut x, mut y] = guess;
    for _ in 0..50 {
        let (ex, ey, j) = distort(&cam.dist, x, y);
        let (rx, ry) = (ex - xd, ey - yd);
        let det = j[0] * j[3] - j[1] * j[2];
        if !det.is_finite() || det <= 1e-6 {
            return None;
        }
        let dx = (j[3] * rx - j[1] * ry) / det;
        let dy = (-j[2] * rx + j[0] * ry) / det;
        x -= dx;
        y -= dy;
        if (rx * cam.fx).abs() < 1e-10 && (ry * cam.fy).abs() < 1e-10 {
            return Some([x, y]);
        }
    }
    None
}

/// A quad in the camera frame, ready for intersection.
struct CamQuad<'a> {
    origin: [f64; 3],
    ex: [f64; 3],
    ey: [f64; 3],
    normal: [f64; 3],
    n_dot_o: f64,
    min: [f64; 2],
    max: [f64; 2],
    texture: &'a dyn Texture,
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

const MISS: u32 = u32::MAX;

/// The nearest hit of the ray `t · (x, y, 1)`.
#[derive(Debug, Clone, Copy)]
struct Hit {
    quad: u32,
    t: f64,
    tex: TexSample,
    /// Where on the quad, in its own coordinates.
    at: [f64; 2],
}

const NO_HIT: Hit = Hit {
    quad: MISS,
    t: 0.0,
    at: [0.0; 2],
    tex: TexSample {
        reflectance: 0.0,
        region: 0,
    },
};

fn cast(quads: &[CamQuad<'_>], ray: [f64; 2]) -> Hit {
    let d = [ray[0], ray[1], 1.0];
    let mut best: Option<(usize, f64, f64, f64)> = None;
    for (k, q) in quads.iter().enumerate() {
        let denom = dot(&q.normal, &d);
        if denom.abs() < 1e-12 {
            continue;
        }
        let t = q.n_dot_o / denom;
        if t <= 1e-6 || best.is_some_and(|b| t >= b.1) {
            continue;
        }
        let rel = [
            d[0] * t - q.origin[0],
            d[1] * t - q.origin[1],
            t - q.origin[2],
        ];
        let (lx, ly) = (dot(&rel, &q.ex), dot(&rel, &q.ey));
        if lx >= q.min[0] && lx <= q.max[0] && ly >= q.min[1] && ly <= q.max[1] {
            best = Some((k, t, lx, ly));
        }
    }
    match best {
        Some((k, t, lx, ly)) => Hit {
            quad: k as u32,
            t,
            tex: quads[k].texture.sample(lx, ly),
            at: [lx, ly],
        },
        None => NO_HIT,
    }
}

/// Renders through one camera. Building it undistorts every pixel corner once, so
/// reuse it for all frames of the same camera.
#[derive(Debug, Clone)]
pub struct Renderer {
    camera: CameraModel,
    /// Normalised coordinates of the pixel corners `(u − ½, v − ½)`, row-major over
    /// `(width + 1) × (height + 1)`; NaN where the lens model has no inverse.
    corners: Vec<[f64; 2]>,
}

/// The light and exposure folded into the camera frame for one frame.
struct Shading {
    to_light: [f64; 3],
    grad0: f64,
    grad: [f64; 3],
    lux: f64,
    ambient: f64,
    dn_per_lux: f64,
    background: f64,
}

impl Shading {
    /// [`Shading::shade`] per colour channel: the print's tint (luminance 1) times the
    /// grey value, with no channel reflecting more than all the light.
    fn shade_rgb(&self, quads: &[CamQuad<'_>], hit: &Hit, ray: [f64; 2]) -> [f64; 3] {
        let grey = self.shade(quads, hit, ray);
        if hit.quad == MISS {
            return [grey; 3];
        }
        let tint = quads[hit.quad as usize].texture.tint(hit.at[0], hit.at[1]);
        let r = hit.tex.reflectance as f64;
        let cap = if r > 0.0 { 1.0 / r } else { 1.0 };
        tint.map(|t| grey * (t as f64).min(cap))
    }

    fn shade(&self, quads: &[CamQuad<'_>], hit: &Hit, ray: [f64; 2]) -> f64 {
        if hit.quad == MISS {
            return self.background;
        }
        let q = &quads[hit.quad as usize];
        let d = [ray[0], ray[1], 1.0];
        // The visible face's normal points back towards the camera.
        let facing = if dot(&q.normal, &d) > 0.0 { -1.0 } else { 1.0 };
        let cos = (facing * dot(&q.normal, &self.to_light)).max(0.0);
        let p = [d[0] * hit.t, d[1] * hit.t, hit.t];
        let gradient = (self.grad0 + dot(&self.grad, &p)).max(0.0);
        let e = self.lux * (self.ambient + (1.0 - self.ambient) * cos) * gradient;
        self.dn_per_lux * e * hit.tex.reflectance as f64
    }
}

impl Renderer {
    /// Prepares rendering through `camera`.
    pub fn new(camera: &CameraModel) -> Result<Renderer, SimError> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        if w == 0 || h == 0 || w > 16384 || h > 16384 {
            return Err(SimError::invalid(
                "camera",
                format!("image size {w}x{h} must be between 1x1 and 16384x16384"),
            ));
        }
        let mut corners = vec![[f64::NAN; 2]; (w + 1) * (h + 1)];
        let mut row_start = [
            (-0.5 - camera.cx) / camera.fx,
            (-0.5 - camera.cy) / camera.fy,
        ];
        for v in 0..=h {
            let mut guess = row_start;
            for u in 0..=w {
                let (pu, pv) = (u as f64 - 0.5, v as f64 - 0.5);
                let linear = [(pu - camera.cx) / camera.fx, (pv - camera.cy) / camera.fy];
                let n =
                    undistort(camera, pu, pv, guess).or_else(|| undistort(camera, pu, pv, linear));
                if let Some(n) = n {
                    corners[v * (w + 1) + u] = n;
                    guess = n;
                    if u == 0 {
                        row_start = n;
                    }
                }
            }
        }
        Ok(Renderer {
            camera: camera.clone(),
            corners,
        })
    }

    /// The camera.
    pub fn camera(&self) -> &CameraModel {
        &self.camera
    }

    /// Renders `scene` seen from `camera_from_world`.
    pub fn render(
        &self,
        camera_from_world: &Iso3,
        scene: &SceneGeometry,
        settings: &RenderSettings,
    ) -> Irradiance {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let quads: Vec<CamQuad<'_>> = scene
            .quads
            .iter()
            .map(|q| {
                let m = camera_from_world * q.world_from_quad;
                let a = |v: Vector3<f64>| {
                    let r = m.rotation * v;
                    [r.x, r.y, r.z]
                };
                let o = m.translation.vector;
                let origin = [o.x, o.y, o.z];
                let normal = a(Vector3::z());
                CamQuad {
                    origin,
                    ex: a(Vector3::x()),
                    ey: a(Vector3::y()),
                    normal,
                    n_dot_o: dot(&normal, &origin),
                    min: q.min,
                    max: q.max,
                    texture: q.texture.as_ref(),
                }
            })
            .collect();
        let flags = self.vertex_flags(camera_from_world, scene);
        let shading = self.shading(camera_from_world, settings);

        let edge_pattern = sample_pattern(settings.edge_samples);
        let varying_pattern = sample_pattern(settings.varying_samples);
        let mut dn = vec![0f32; w * h];
        let mut depth = vec![0f32; w * h];
        let mut rgb = if settings.colour {
            vec![[0f32; 3]; w * h]
        } else {
            vec![]
        };
        let cast_row = |v: usize| -> Vec<Hit> {
            self.corners[v * (w + 1)..(v + 1) * (w + 1)]
                .iter()
                .map(|&c| {
                    if c[0].is_nan() {
                        NO_HIT
                    } else {
                        cast(&quads, c)
                    }
                })
                .collect()
        };
        let mut upper = cast_row(0);
        for v in 0..h {
            let lower = cast_row(v + 1);
            let c0 = &self.corners[v * (w + 1)..(v + 1) * (w + 1)];
            let c1 = &self.corners[(v + 1) * (w + 1)..(v + 2) * (w + 1)];
            for u in 0..w {
                let quad_corners = [c0[u], c0[u + 1], c1[u], c1[u + 1]];
                if quad_corners.iter().any(|c| c[0].is_nan()) {
                    dn[v * w + u] = shading.background as f32;
                    if settings.colour {
                        rgb[v * w + u] = [shading.background as f32; 3];
                    }
                    continue;
                }
                let lerp = |s: f64, t: f64| {
                    let top = [
                        quad_corners[0][0] + (quad_corners[1][0] - quad_corners[0][0]) * s,
                        quad_corners[0][1] + (quad_corners[1][1] - quad_corners[0][1]) * s,
                    ];
                    let bottom = [
                        quad_corners[2][0] + (quad_corners[3][0] - quad_corners[2][0]) * s,
                        quad_corners[2][1] + (quad_corners[3][1] - quad_corners[2][1]) * s,
                    ];
                    [
                        top[0] + (bottom[0] - top[0]) * t,
                        top[1] + (bottom[1] - top[1]) * t,
                    ]
                };
                let centre_ray = lerp(0.5, 0.5);
                let centre = cast(&quads, centre_ray);
                depth[v * w + u] = if centre.quad == MISS {
                    0.0
                } else {
                    centre.t as f32
                };
                let hits = [upper[u], upper[u + 1], lower[u], lower[u + 1]];
                let same = hits.iter().all(|h| {
                    h.quad == centre.quad && (h.quad == MISS || h.tex.region == centre.tex.region)
                });
                let pattern = if !same || flags[v * w + u] {
                    Some(&edge_pattern)
                } else if centre.quad != MISS && centre.tex.region == VARYING {
                    Some(&varying_pattern)
                } else {
                    None
                };
                let value = if let Some(pattern) = pattern {
                    let sum: f64 = pattern
                        .iter()
                        .map(|&(s, t)| {
                            let ray = lerp(s, t);
                            shading.shade(&quads, &cast(&quads, ray), ray)
                        })
                        .sum();
                    sum / pattern.len() as f64
                } else {
                    shading.shade(&quads, &centre, centre_ray)
                };
                dn[v * w + u] = value as f32;
                if settings.colour {
                    let c = if let Some(pattern) = pattern {
                        let mut sum = [0.0; 3];
                        for &(s, t) in pattern.iter() {
                            let ray = lerp(s, t);
                            let c = shading.shade_rgb(&quads, &cast(&quads, ray), ray);
                            (0..3).for_each(|k| sum[k] += c[k]);
                        }
                        sum.map(|v| v / pattern.len() as f64)
                    } else {
                        shading.shade_rgb(&quads, &centre, centre_ray)
                    };
                    rgb[v * w + u] = c.map(|v| v as f32);
                }
            }
            upper = lower;
        }
        let mut out = Irradiance {
            width: w,
            height: h,
            dn,
            depth_m: depth,
            rgb,
        };
        self.apply_optics(&mut out, &settings.optics);
        out
    }

    /// Pixels (with their 8 neighbours) that hold a projected quad vertex: there a
    /// surface may poke into a pixel between its corner rays.
    fn vertex_flags(&self, camera_from_world: &Iso3, scene: &SceneGeometry) -> Vec<bool> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let mut flags = vec![false; w * h];
        for q in &scene.quads {
            for (x, y) in [
                (q.min[0], q.min[1]),
                (q.max[0], q.min[1]),
                (q.min[0], q.max[1]),
                (q.max[0], q.max[1]),
            ] {
                let p = camera_from_world * q.world_from_quad * Point3::new(x, y, 0.0);
                let Some(uv) = self.camera.project(&p) else {
                    continue;
                };
                let (cu, cv) = (uv.x.round(), uv.y.round());
                for dv in -1..=1 {
                    for du in -1..=1 {
                        let (pu, pv) = (cu + du as f64, cv + dv as f64);
                        if pu >= 0.0 && pv >= 0.0 && pu < w as f64 && pv < h as f64 {
                            flags[pv as usize * w + pu as usize] = true;
                        }
                    }
                }
            }
        }
        flags
    }

    fn shading(&self, camera_from_world: &Iso3, s: &RenderSettings) -> Shading {
        let l = &s.lighting;
        let to_light = Vector3::from(l.towards_light);
        let to_light = if to_light.norm() > 0.0 {
            camera_from_world.rotation * to_light.normalize()
        } else {
            Vector3::zeros()
        };
        // 1 + g·(p_world − o) with p_world = R^T (p_cam − t): linear in p_cam.
        let g = Vector3::from(l.gradient_per_m);
        let world_from_camera = camera_from_world.inverse();
        let g_cam = camera_from_world.rotation * g;
        let o = Vector3::from(l.gradient_origin);
        let grad0 = 1.0 + g.dot(&(world_from_camera.translation.vector - o));
        Shading {
            to_light: [to_light.x, to_light.y, to_light.z],
            grad0,
            grad: [g_cam.x, g_cam.y, g_cam.z],
            lux: l.lux,
            ambient: l.ambient.clamp(0.0, 1.0),
            dn_per_lux: s.dn_per_lux,
            background: s.background_dn,
        }
    }

    /// Defocus + PSF (a separable Gaussian whose σ follows each pixel's depth), then
    /// vignetting.
    fn apply_optics(&self, img: &mut Irradiance, optics: &Optics) {
        let (w, h) = (img.width, img.height);
        let cam = &self.camera;
        let sigma: Vec<f32> = img
            .depth_m
            .iter()
            .map(|&z| {
                let inv_z = if z > 0.0 { 1.0 / z as f64 } else { 0.0 };
                let focus = if optics.focus_m > 0.0 {
                    1.0 / optics.focus_m
                } else {
                    0.0
                };
                let coc = cam.fx * optics.aperture_m * (inv_z - focus).abs();
                ((coc / 4.0).powi(2) + optics.psf_sigma_px.powi(2)).sqrt() as f32
            })
            .collect();
        if sigma.iter().any(|&s| s > 0.01) {
            let mut kernels = KernelCache::default();
            if !img.rgb.is_empty() {
                for k in 0..3 {
                    let mut channel: Vec<f32> = img.rgb.iter().map(|c| c[k]).collect();
                    blur(&mut channel, &sigma, w, h, &mut kernels);
                    for (c, v) in img.rgb.iter_mut().zip(channel) {
                        c[k] = v;
                    }
                }
            }
            blur(&mut img.dn, &sigma, w, h, &mut kernels);
        }
        if optics.vignetting > 0.0 {
            let s = optics.vignetting.clamp(0.0, 1.0);
            for v in 0..h {
                for u in 0..w {
                    let c = [
                        self.corners[v * (w + 1) + u],
                        self.corners[(v + 1) * (w + 1) + u + 1],
                    ];
                    let (x, y) = ((c[0][0] + c[1][0]) / 2.0, (c[0][1] + c[1][1]) / 2.0);
                    if x.is_nan() {
                        continue;
                    }
                    let cos2 = 1.0 / (1.0 + x * x + y * y);
                    let f = (1.0 - s * (1.0 - cos2 * cos2)) as f32;
                    img.dn[v * w + u] *= f;
                    if let Some(c) = img.rgb.get_mut(v * w + u) {
                        c.iter_mut().for_each(|x| *x *= f);
                    }
                }
            }
        }
    }
}

/// At least `n` sample positions in the unit pixel: a Fibonacci lattice
/// `((i + ½)/F_k, frac((i·F_{k−1} + ½)/F_k))` with `F_k` the smallest Fibonacci number
/// `>= n`. Unlike an `m × m` grid, which quantises the coverage of a near-axis-aligned
/// edge to `1/m` steps, the lattice is stratified along both axes and has about the
/// lowest discrepancy for half-planes of every orientation, so an edge's coverage is
/// resolved to ~1/F_k. (Measured in the tests: with 377 samples the rendered board
/// matches the analytic box filter to 0.01 of the contrast per pixel.)
fn sample_pattern(n: usize) -> Vec<(f64, f64)> {
    let (mut a, mut b) = (1usize, 1usize);
    while b < n {
        (a, b) = (b, a + b);
    }
    (0..b)
        .map(|i| {
            (
                (i as f64 + 0.5) / b as f64,
                (((i * a) % b) as f64 + 0.5) / b as f64,
            )
        })
        .collect()
}

/// The separable depth-dependent Gaussian of [`Renderer::apply_optics`] on one channel.
fn blur(img: &mut [f32], sigma: &[f32], w: usize, h: usize, kernels: &mut KernelCache) {
    let mut tmp = vec![0f32; w * h];
    for v in 0..h {
        for u in 0..w {
            let k = kernels.get(sigma[v * w + u]);
            tmp[v * w + u] = convolve(k, |i| {
                let x = (u as isize + i).clamp(0, w as isize - 1) as usize;
                img[v * w + x]
            });
        }
    }
    for v in 0..h {
        for u in 0..w {
            let k = kernels.get(sigma[v * w + u]);
            img[v * w + u] = convolve(k, |i| {
                let y = (v as isize + i).clamp(0, h as isize - 1) as usize;
                tmp[y * w + u]
            });
        }
    }
}

fn convolve(kernel: &[f32], at: impl Fn(isize) -> f32) -> f32 {
    let r = (kernel.len() / 2) as isize;
    kernel
        .iter()
        .enumerate()
        .map(|(k, wgt)| wgt * at(k as isize - r))
        .sum()
}

/// Normalised 1-D Gaussian kernels by σ quantised to 1/64 px.
#[derive(Default)]
struct KernelCache {
    kernels: Vec<Option<Vec<f32>>>,
}

impl KernelCache {
    fn get(&mut self, sigma: f32) -> &[f32] {
        let key = (sigma.clamp(0.0, 16.0) * 64.0).round() as usize;
        if self.kernels.len() <= key {
            self.kernels.resize(key + 1, None);
        }
        self.kernels[key].get_or_insert_with(|| {
            let s = key as f32 / 64.0;
            if s < 0.01 {
                return vec![1.0];
            }
            let r = (3.5 * s).ceil() as i32;
            let mut k: Vec<f32> = (-r..=r)
                .map(|i| (-(i * i) as f32 / (2.0 * s * s)).exp())
                .collect();
            let total: f32 = k.iter().sum();
            k.iter_mut().for_each(|v| *v /= total);
            k
        })
    }
}

/// The inner corners of a checkerboard seen from `camera_from_target`, projected with
/// the camera model: the exact positions a detector should find, in the order of
/// `b2b_calib::synth::board_points` (row by row). `None` for corners behind the camera.
pub fn checkerboard_corners_px(
    camera: &CameraModel,
    camera_from_target: &Iso3,
    board: &Checkerboard,
) -> Vec<Option<nalgebra::Point2<f64>>> {
    let [c, r] = board.inner_corners;
    b2b_calib::synth::board_points(c as usize, r as usize, board.square_m)
        .iter()
        .map(|p| camera.project(&(camera_from_target * p)))
        .collect()
}

#[cfg(test)]
mod tests;
