//! The renderer against the analytic projection.
//!
//! The reference is the exact box-filtered image: every square of the board projected
//! with `CameraModel::project` (each edge sampled densely when the lens distorts, so the
//! polygon follows the curved image of the edge), clipped against every pixel square,
//! its area taken. The renderer must agree pixel by pixel, in each dark square's
//! centroid and in its area (which measures the mean edge offset).

use super::*;
use crate::texture::{NoiseTexture, Uniform};
use nalgebra::Point2;

fn camera(dist: &[f64]) -> CameraModel {
    CameraModel::new(320, 240, [300.0, 301.0, 159.63, 120.27], dist).unwrap()
}

fn board() -> Checkerboard {
    Checkerboard::new([7, 5], 0.03, 0.015)
}

/// A tilted, rolled board about 0.45 m in front of the camera, filling most of the view.
fn camera_from_target() -> Iso3 {
    Iso3::from_parts(
        Translation3::new(-0.095, -0.06, 0.45),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.35, -0.25, 0.12)),
    )
}

type Poly = Vec<[f64; 2]>;

fn clip(poly: &Poly, keep: impl Fn(&[f64; 2]) -> f64) -> Poly {
    // Sutherland-Hodgman against the half plane keep(p) >= 0 (keep is affine).
    let mut out = vec![];
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
        let (fa, fb) = (keep(&a), keep(&b));
        if fa >= 0.0 {
            out.push(a);
        }
        if (fa >= 0.0) != (fb >= 0.0) {
            let t = fa / (fa - fb);
            out.push([a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t]);
        }
    }
    out
}

fn area(poly: &Poly) -> f64 {
    let mut s = 0.0;
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
        s += a[0] * b[1] - b[0] * a[1];
    }
    (s / 2.0).abs()
}

/// The image of the rectangle `[x0, x1] × [y0, y1]` of the target, each edge sampled
/// `n` times.
fn project_rect(cam: &CameraModel, pose: &Iso3, lo: [f64; 2], hi: [f64; 2], n: usize) -> Poly {
    let corners = [
        [lo[0], lo[1]],
        [hi[0], lo[1]],
        [hi[0], hi[1]],
        [lo[0], hi[1]],
    ];
    let mut poly = vec![];
    for k in 0..4 {
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        for i in 0..n {
            let t = i as f64 / n as f64;
            let p = Point3::new(a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, 0.0);
            let uv = cam.project(&(pose * p)).unwrap();
            poly.push([uv.x, uv.y]);
        }
    }
    poly
}

/// Adds `weight ×` the coverage of `poly` to every pixel of `img`.
fn rasterise(img: &mut [f64], w: usize, h: usize, poly: &Poly, weight: f64) {
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for p in poly {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let u0 = (lo[0].floor() as isize - 1).max(0) as usize;
    let v0 = (lo[1].floor() as isize - 1).max(0) as usize;
    let u1 = ((hi[0].ceil() as isize + 1).max(0) as usize).min(w - 1);
    let v1 = ((hi[1].ceil() as isize + 1).max(0) as usize).min(h - 1);
    for v in v0..=v1 {
        for u in u0..=u1 {
            let (uf, vf) = (u as f64, v as f64);
            let mut p = clip(poly, |q| q[0] - (uf - 0.5));
            p = clip(&p, |q| (uf + 0.5) - q[0]);
            p = clip(&p, |q| q[1] - (vf - 0.5));
            p = clip(&p, |q| (vf + 0.5) - q[1]);
            if p.len() >= 3 {
                img[v * w + u] += weight * area(&p);
            }
        }
    }
}

struct Comparison {
    max_pixel_error: f64,
    rms_pixel_error: f64,
    max_centroid_error: f64,
    max_edge_offset: f64,
    squares: usize,
}

/// Renders the board and compares with the analytic box-filtered image. Errors are in
/// units of the black-white contrast (pixels) and pixels (centroids, edge offsets).
fn compare(cam: &CameraModel, settings: &RenderSettings) -> Comparison {
    let pose = camera_from_target();
    let b = board();
    let mut scene = SceneGeometry::default();
    scene.add_checkerboard(Iso3::identity(), b);
    let img = Renderer::new(cam).unwrap().render(&pose, &scene, settings);

    let (w, h) = (cam.width as usize, cam.height as usize);
    let white = settings.dn_per_lux * settings.lighting.lux * b.white as f64;
    let black = settings.dn_per_lux * settings.lighting.lux * b.black as f64;
    let bg = settings.background_dn;
    let n = if cam.dist.iter().any(|d| *d != 0.0) {
        64
    } else {
        1
    };
    let mut expected = vec![bg; w * h];
    let mut dark = vec![0.0; w * h];
    let (lo, hi) = b.extent();
    rasterise(
        &mut expected,
        w,
        h,
        &project_rect(cam, &pose, lo, hi, n),
        white - bg,
    );
    let s = b.square_m;
    let mut squares = vec![];
    for bb in -1..b.inner_corners[1] as i64 {
        for a in -1..b.inner_corners[0] as i64 {
            if Checkerboard::is_black(a, bb) {
                let lo = [a as f64 * s, bb as f64 * s];
                let hi = [lo[0] + s, lo[1] + s];
                let poly = project_rect(cam, &pose, lo, hi, n);
                rasterise(&mut expected, w, h, &poly, black - white);
                rasterise(&mut dark, w, h, &poly, 1.0);
                squares.push(poly);
            }
        }
    }
    let contrast = white - black;
    let errors: Vec<f64> = (0..w * h)
        .map(|i| (img.dn[i] as f64 - expected[i]) / contrast)
        .collect();
    let max_pixel_error = errors.iter().fold(0.0f64, |m, e| m.max(e.abs()));
    let rms_pixel_error = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();

    // Per dark square: darkness-weighted centroid and area, over a window around it
    // that lies on the board (so only white surrounds it).
    let mut max_centroid_error = 0.0f64;
    let mut max_edge_offset = 0.0f64;
    let mut count = 0;
    for poly in &squares {
        let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
        for p in poly {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let (u0, v0) = (lo[0].floor() as isize - 1, lo[1].floor() as isize - 1);
        let (u1, v1) = (hi[0].ceil() as isize + 1, hi[1].ceil() as isize + 1);
        if u0 < 0 || v0 < 0 || u1 >= w as isize || v1 >= h as isize {
            continue;
        }
        // Dark squares touch diagonally: remove the neighbours' (analytic) share.
        let mut this = vec![0.0; w * h];
        rasterise(&mut this, w, h, poly, 1.0);
        let moments = |values: &dyn Fn(usize) -> f64| {
            let (mut m0, mut mu, mut mv) = (0.0, 0.0, 0.0);
            for v in v0..=v1 {
                for u in u0..=u1 {
                    let i = v as usize * w + u as usize;
                    let d = (white - values(i)) / contrast - (dark[i] - this[i]);
                    m0 += d;
                    mu += d * u as f64;
                    mv += d * v as f64;
                }
            }
            (m0, mu / m0, mv / m0)
        };
        let (a_r, u_r, v_r) = moments(&|i| img.dn[i] as f64);
        let (a_e, u_e, v_e) = moments(&|i| expected[i]);
        // The windows touch only white paper, so the analytic area is the polygon's.
        assert!(
            (a_e - area(poly)).abs() < 1e-6 * area(poly),
            "{a_e} vs {}",
            area(poly)
        );
        let perimeter: f64 = (0..poly.len())
            .map(|i| {
                let (p, q) = (poly[i], poly[(i + 1) % poly.len()]);
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()
            })
            .sum();
        max_centroid_error =
            max_centroid_error.max(((u_r - u_e).powi(2) + (v_r - v_e).powi(2)).sqrt());
        max_edge_offset = max_edge_offset.max(((a_r - a_e) / perimeter).abs());
        count += 1;
    }
    Comparison {
        max_pixel_error,
        rms_pixel_error,
        max_centroid_error,
        max_edge_offset,
        squares: count,
    }
}

#[test]
fn distort_matches_the_calib_camera_model() {
    let cam = camera(&[-0.25, 0.08, 0.001, -0.0005, 0.01]);
    for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4), (0.1, 0.45)] {
        let (xd, yd, _) = distort(&cam.dist, x, y);
        let uv = cam.project(&Point3::new(x, y, 1.0)).unwrap();
        assert!((cam.fx * xd + cam.cx - uv.x).abs() < 1e-12);
        assert!((cam.fy * yd + cam.cy - uv.y).abs() < 1e-12);
        let back = undistort(&cam, uv.x, uv.y, [0.0, 0.0]).unwrap();
        assert!((back[0] - x).abs() < 1e-12 && (back[1] - y).abs() < 1e-12);
    }
}

#[test]
fn pinhole_rendering_matches_the_analytic_box_filter() {
    let c = compare(&camera(&[]), &RenderSettings::ideal());
    eprintln!(
        "pinhole: max pixel error {:.4}, rms {:.5} (contrast units); centroid max {:.5} px; \
         edge offset max {:.5} px over {} squares",
        c.max_pixel_error, c.rms_pixel_error, c.max_centroid_error, c.max_edge_offset, c.squares
    );
    assert!(c.squares >= 15);
    // Measured: 0.0086, 0.0008 px, 0.0003 px (377 samples per edge pixel).
    assert!(c.max_pixel_error < 0.02, "{}", c.max_pixel_error);
    assert!(c.max_centroid_error < 0.003, "{}", c.max_centroid_error);
    assert!(c.max_edge_offset < 0.001, "{}", c.max_edge_offset);
}

#[test]
fn distorted_rendering_matches_the_analytic_box_filter() {
    let c = compare(
        &camera(&[-0.28, 0.09, 0.0012, -0.0007, -0.01]),
        &RenderSettings::ideal(),
    );
    eprintln!(
        "distorted: max pixel error {:.4}, rms {:.5}; centroid max {:.5} px; edge offset max {:.5} px \
         over {} squares",
        c.max_pixel_error, c.rms_pixel_error, c.max_centroid_error, c.max_edge_offset, c.squares
    );
    assert!(c.squares >= 15);
    // Measured: 0.013, 0.002 px, 0.0011 px.
    assert!(c.max_pixel_error < 0.025, "{}", c.max_pixel_error);
    assert!(c.max_centroid_error < 0.004, "{}", c.max_centroid_error);
    assert!(c.max_edge_offset < 0.002, "{}", c.max_edge_offset);
}

#[test]
fn symmetric_blur_keeps_squares_where_they_are() {
    let mut settings = RenderSettings::ideal();
    settings.optics = Optics {
        aperture_m: 2e-3,
        focus_m: 0.3,
        psf_sigma_px: 0.6,
        vignetting: 0.0,
    };
    let c = compare(&camera(&[-0.1, 0.0, 0.0, 0.0, 0.0]), &settings);
    eprintln!(
        "blurred: centroid max {:.4} px, edge offset max {:.4} px",
        c.max_centroid_error, c.max_edge_offset
    );
    // Blur moves grey levels between neighbouring pixels (large pixel errors) but not
    // the squares: centroids and areas stay.
    assert!(c.max_pixel_error > 0.1);
    // Measured: 0.005 px, 0.0008 px.
    assert!(c.max_centroid_error < 0.01, "{}", c.max_centroid_error);
    assert!(c.max_edge_offset < 0.002, "{}", c.max_edge_offset);
}

#[test]
fn depth_is_the_exact_z_of_each_pixel_centre_ray() {
    let cam = camera(&[-0.2, 0.05, 0.0, 0.0, 0.0]);
    let pose = camera_from_target();
    let mut scene = SceneGeometry::default();
    scene.add_quad(
        Iso3::identity(),
        [-1.0, -1.0],
        [1.0, 1.0],
        Arc::new(Uniform(0.5)),
    );
    let img = Renderer::new(&cam)
        .unwrap()
        .render(&pose, &scene, &RenderSettings::ideal());
    let n = pose.rotation * Vector3::z();
    let o = pose.translation.vector;
    let mut worst = 0.0f64;
    for (v, u) in [(0, 0), (119, 160), (239, 319), (30, 250)] {
        let ray = cam.unproject(&Point2::new(u as f64, v as f64));
        let d = Vector3::new(ray.x, ray.y, 1.0);
        let z = n.dot(&o) / n.dot(&d);
        worst = worst.max((img.depth_m[v * 320 + u] as f64 - z).abs());
    }
    assert!(worst < 1e-6, "{worst}");
}

#[test]
fn box_faces_point_outwards_and_occlude() {
    let cam = camera(&[]);
    let mut scene = SceneGeometry::default();
    let tex: [Arc<dyn Texture>; 6] =
        std::array::from_fn(|k| Arc::new(Uniform(0.1 + 0.1 * k as f32)) as _);
    scene.add_box(Iso3::translation(0.0, 0.0, 1.0), [0.2, 0.3, 0.4], tex);
    let img =
        Renderer::new(&cam)
            .unwrap()
            .render(&Iso3::identity(), &scene, &RenderSettings::ideal());
    let centre = 120 * 320 + 160;
    // The camera looks along +z at the box: it sees the -z face, 0.2 m before the centre.
    assert!(
        (img.depth_m[centre] - 0.8).abs() < 1e-6,
        "{}",
        img.depth_m[centre]
    );
    let expected = DN_PER_LUX * 352.0 * 0.6;
    assert!(
        (img.dn[centre] as f64 - expected).abs() < 1e-3,
        "{}",
        img.dn[centre]
    );
}

#[test]
fn varying_textures_are_supersampled_and_deterministic() {
    let cam = camera(&[]);
    let mut scene = SceneGeometry::default();
    let noise = NoiseTexture {
        seed: 3,
        scale_m: 0.05,
        octaves: 4,
        mean: 0.5,
        contrast: 0.35,
    };
    scene.add_quad(
        Iso3::translation(0.0, 0.0, 0.6),
        [-1.0, -1.0],
        [1.0, 1.0],
        Arc::new(noise),
    );
    let r = Renderer::new(&cam).unwrap();
    let a = r.render(&Iso3::identity(), &scene, &RenderSettings::ideal());
    let b = r.render(&Iso3::identity(), &scene, &RenderSettings::ideal());
    assert_eq!(a, b);
    let mean = a.dn.iter().map(|&v| v as f64).sum::<f64>() / a.dn.len() as f64;
    let var = a.dn.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / a.dn.len() as f64;
    assert!(var.sqrt() > 20.0, "texture too flat: {}", var.sqrt());
}

#[test]
fn vignetting_darkens_the_corners_by_the_cos4_law() {
    let cam = camera(&[]);
    let mut scene = SceneGeometry::default();
    scene.add_quad(
        Iso3::translation(0.0, 0.0, 1.0),
        [-5.0, -5.0],
        [5.0, 5.0],
        Arc::new(Uniform(0.5)),
    );
    let mut settings = RenderSettings::ideal();
    settings.optics.vignetting = 1.0;
    let img = Renderer::new(&cam)
        .unwrap()
        .render(&Iso3::identity(), &scene, &settings);
    let centre = img.dn[120 * 320 + 160] as f64;
    let corner = img.dn[0] as f64;
    let n = cam.unproject(&Point2::new(0.0, 0.0));
    let cos2 = 1.0 / (1.0 + n.norm_squared());
    assert!(
        (corner / centre - cos2 * cos2).abs() < 0.01,
        "{}",
        corner / centre
    );
}

#[test]
fn colour_channels_have_the_grey_image_as_luminance() {
    let cam = camera(&[]);
    let mut scene = SceneGeometry::default();
    let noise = NoiseTexture {
        seed: 5,
        scale_m: 0.05,
        octaves: 4,
        mean: 0.4,
        contrast: 0.2,
    };
    // A coloured print on the left, the (grey) checkerboard on the right.
    scene.add_quad(
        Iso3::translation(0.0, 0.0, 0.6),
        [-1.0, -1.0],
        [0.0, 1.0],
        Arc::new(noise),
    );
    scene.add_checkerboard(Iso3::translation(0.02, -0.1, 0.6), board());
    let r = Renderer::new(&cam).unwrap();
    let mut settings = RenderSettings::ideal();
    settings.optics = Optics::realsense();
    settings.colour = true;
    let img = r.render(&Iso3::identity(), &scene, &settings);
    assert_eq!(img.rgb.len(), img.dn.len());
    let (mut coloured, mut grey) = (0, 0);
    for (c, &y) in img.rgb.iter().zip(&img.dn) {
        let lum = 0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2];
        // Tints with luminance 1: the grey image is the colour image's luminance
        // (no tint is clipped at these reflectances).
        assert!((lum - y).abs() < 1e-3 * y.max(1.0), "{c:?} vs {y}");
        let spread =
            c.iter().cloned().fold(f32::MIN, f32::max) - c.iter().cloned().fold(f32::MAX, f32::min);
        if spread > 0.1 * y {
            coloured += 1;
        } else if spread < 1e-4 * y.max(1.0) {
            grey += 1;
        }
    }
    // The print is coloured, the board and the background are grey.
    assert!(coloured > img.dn.len() / 4, "{coloured}");
    assert!(grey > img.dn.len() / 4, "{grey}");
    // Without colour, the grey image is the same and no channels are made.
    settings.colour = false;
    let plain = r.render(&Iso3::identity(), &scene, &settings);
    assert!(plain.rgb.is_empty());
    assert_eq!(plain.dn, img.dn);
}
