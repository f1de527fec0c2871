//! Depth aligned to colour: a D4xx's depth comes from its stereo imagers, at
//! their resolution and position; the agent wants it per colour pixel.
//!
//! Each depth pixel is lifted to its 3-D patch (its two opposite corners at its
//! depth, through the depth stream's pinhole), carried into the colour camera by
//! `colour_from_depth` and projected through the colour intrinsics (with their
//! Brown-Conrady distortion); every colour pixel the patch covers takes the
//! depth in the colour frame, and where patches overlap the nearest wins (a
//! z-test: where the colour camera looks past an edge that the depth sensor sees
//! from its side, the nearer surface is the one in view). Colour pixels no depth
//! pixel reaches (seen by colour, hidden from depth) stay 0.
//!
//! Ours rather than librealsense's align block: it needs no librealsense, so it
//! is tested and benchmarked everywhere (`benches/align.rs`, against OpenCV's
//! `rgbd::registerDepth`), and held to 1 px at edges on rendered D435
//! recordings played through librealsense (`services/tests/realsense_bag.rs`).

use crate::{FrameHeader, FramesError};

/// Checks that a stream's header carries intrinsics.
fn check_intrinsics(h: &FrameHeader, what: &str) -> Result<(), FramesError> {
    if !(h.fx > 0.0 && h.fy > 0.0 && h.fx.is_finite() && h.fy.is_finite()) {
        return Err(FramesError::Align(format!(
            "the {what} stream has no intrinsics"
        )));
    }
    Ok(())
}

/// Projects a point through a header's pinhole and its Brown-Conrady
/// distortion `k1, k2, p1, p2, k3`.
fn project(h: &FrameHeader, p: [f64; 3]) -> Option<[f64; 2]> {
    if p[2] <= 0.0 {
        return None;
    }
    let (x, y) = (p[0] / p[2], p[1] / p[2]);
    let [k1, k2, p1, p2, k3] = h.dist;
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    Some([h.fx * xd + h.cx, h.fy * yd + h.cy])
}

/// `colour_from_depth` as a row-major rotation and a translation (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extrinsic {
    pub rotation: [f64; 9],
    pub translation_m: [f64; 3],
}

impl Extrinsic {
    /// The inverse of a header's `depth_from_colour`.
    pub fn colour_from_depth(h: &FrameHeader) -> Extrinsic {
        let r = h.depth_from_colour_rotation;
        let t = h.depth_from_colour_translation_m;
        // Rᵀ and -Rᵀ t.
        let rt = [r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]];
        let translation_m =
            [0, 1, 2].map(|i| -(rt[3 * i] * t[0] + rt[3 * i + 1] * t[1] + rt[3 * i + 2] * t[2]));
        Extrinsic {
            rotation: rt,
            translation_m,
        }
    }
}

/// Aligns `depth` (row-major, the size of `depth_stream`, in units of
/// `unit_m`; 0 = none) to the colour camera: `out` (the size of
/// `colour_stream`, same unit) is overwritten. The headers give each stream's
/// size and intrinsics; the depth stream must be undistorted (a D4xx's is).
pub fn align_to_colour(
    depth: &[u16],
    depth_stream: &FrameHeader,
    colour_stream: &FrameHeader,
    colour_from_depth: &Extrinsic,
    unit_m: f64,
    out: &mut [u16],
) -> Result<(), FramesError> {
    check_intrinsics(depth_stream, "depth")?;
    check_intrinsics(colour_stream, "colour")?;
    let (dw, dh) = (depth_stream.width as usize, depth_stream.height as usize);
    let (cw, ch) = (colour_stream.width as usize, colour_stream.height as usize);
    if depth.len() != dw * dh {
        return Err(FramesError::Align(format!(
            "{} depth values for a {dw}x{dh} depth stream",
            depth.len()
        )));
    }
    if out.len() != cw * ch {
        return Err(FramesError::Align(format!(
            "a {}-pixel output for a {cw}x{ch} colour stream",
            out.len()
        )));
    }
    if depth_stream.dist.iter().any(|d| *d != 0.0) {
        return Err(FramesError::Align(
            "the depth stream carries distortion; only undistorted depth (as a D4xx delivers) is aligned"
                .into(),
        ));
    }
    if !(unit_m > 0.0 && unit_m.is_finite()) {
        return Err(FramesError::Align(format!("depth unit {unit_m} m")));
    }
    out.fill(0);
    let d = depth_stream;
    let c = colour_stream;
    let r = &colour_from_depth.rotation;
    let t = colour_from_depth.translation_m;
    // A corner of depth pixel (u, v) at depth z lands at
    // z (x_u R[:,0] + y_v R[:,1] + R[:,2]) + t in the colour camera: the column
    // and row terms are computed once per pixel edge.
    let col = |k: usize| [r[k], r[3 + k], r[6 + k]];
    let (c0, c1, c2) = (col(0), col(1), col(2));
    let xs: Vec<[f64; 3]> = (0..=dw)
        .map(|u| {
            let x = (u as f64 - 0.5 - d.cx) / d.fx;
            [x * c0[0], x * c0[1], x * c0[2]]
        })
        .collect();
    let ys: Vec<[f64; 3]> = (0..=dh)
        .map(|v| {
            let y = (v as f64 - 0.5 - d.cy) / d.fy;
            [y * c1[0] + c2[0], y * c1[1] + c2[1], y * c1[2] + c2[2]]
        })
        .collect();
    let distorted = c.dist.iter().any(|k| *k != 0.0);
    let project = |q: [f64; 3]| -> Option<[f64; 2]> {
        if distorted {
            return project(c, q);
        }
        if q[2] <= 0.0 {
            return None;
        }
        let w = 1.0 / q[2];
        Some([c.fx * q[0] * w + c.cx, c.fy * q[1] * w + c.cy])
    };
    let (cwi, chi) = (cw as i64 - 1, ch as i64 - 1);
    for v in 0..dh {
        let (ya, yb) = (ys[v], ys[v + 1]);
        for u in 0..dw {
            let raw = depth[v * dw + u];
            if raw == 0 {
                continue;
            }
            let z = f64::from(raw) * unit_m;
            let (xa, xb) = (xs[u], xs[u + 1]);
            let corner = |x: [f64; 3], y: [f64; 3]| {
                [
                    z * (x[0] + y[0]) + t[0],
                    z * (x[1] + y[1]) + t[1],
                    z * (x[2] + y[2]) + t[2],
                ]
            };
            let (qa, qb) = (corner(xa, ya), corner(xb, yb));
            let (Some(a), Some(b)) = (project(qa), project(qb)) else {
                continue;
            };
            let zc = 0.5 * (qa[2] + qb[2]) / unit_m;
            if !(1.0..65535.5).contains(&zc) {
                continue;
            }
            // Positive: +0.5 and truncation round it (no libm call).
            let zc = (zc + 0.5) as u16;
            // The colour pixels whose centres the patch covers (at least one).
            let (amin, amax) = (a[0].min(b[0]), a[0].max(b[0]));
            let (bmin, bmax) = (a[1].min(b[1]), a[1].max(b[1]));
            let (mut u0, mut u1) = (ceil_i(amin).max(0), floor_i(amax).min(cwi));
            let (mut v0, mut v1) = (ceil_i(bmin).max(0), floor_i(bmax).min(chi));
            if u0 > u1 || v0 > v1 {
                // Smaller than a colour pixel: the one holding its centre.
                let cu = floor_i(0.5 * (amin + amax) + 0.5);
                let cv = floor_i(0.5 * (bmin + bmax) + 0.5);
                if !(0..=cwi).contains(&cu) || !(0..=chi).contains(&cv) {
                    continue;
                }
                (u0, u1, v0, v1) = (cu, cu, cv, cv);
            }
            let (u0, u1) = (u0 as usize, u1 as usize);
            for y in v0 as usize..=v1 as usize {
                for px in &mut out[y * cw + u0..=y * cw + u1] {
                    if *px == 0 || zc < *px {
                        *px = zc;
                    }
                }
            }
        }
    }
    Ok(())
}

/// `floor` and `ceil` to integers by truncation: `f64::floor` is a libm call on
/// x86-64 without SSE4.1, and this loop runs them four times per depth pixel.
/// Values far outside `i64` saturate, which the clamps above handle.
fn floor_i(x: f64) -> i64 {
    let t = x as i64;
    t - i64::from((t as f64) > x)
}

fn ceil_i(x: f64) -> i64 {
    let t = x as i64;
    t + i64::from((t as f64) < x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole(w: u32, h: u32, f: f64) -> FrameHeader {
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        FrameHeader::new(crate::StreamKind::Z16, w, h).with_intrinsics(f, f, cx, cy, [0.0; 5])
    }

    const IDENTITY: Extrinsic = Extrinsic {
        rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        translation_m: [0.0; 3],
    };

    #[test]
    fn the_same_camera_maps_every_pixel_onto_itself() {
        let k = pinhole(64, 48, 60.0);
        let depth: Vec<u16> = (0..64 * 48).map(|i| 500 + (i % 7) as u16).collect();
        let mut out = vec![0; 64 * 48];
        align_to_colour(&depth, &k, &k, &IDENTITY, 0.001, &mut out).unwrap();
        assert_eq!(out, depth);
    }

    #[test]
    fn a_step_lands_where_the_colour_camera_sees_it_and_the_nearer_surface_wins() {
        // Depth and colour 50 mm apart along x; a near plane (0.4 m) on the
        // left half of the depth image, a far one (1.0 m) on the right.
        let (w, h) = (320u32, 240u32);
        let k = pinhole(w, h, 300.0);
        let depth: Vec<u16> = (0..(w * h) as usize)
            .map(|i| if (i % w as usize) < 160 { 400 } else { 1000 })
            .collect();
        let e = Extrinsic {
            translation_m: [-0.05, 0.0, 0.0],
            ..IDENTITY
        };
        let mut out = vec![0; (w * h) as usize];
        align_to_colour(&depth, &k, &k, &e, 0.001, &mut out).unwrap();
        // The near plane's edge: depth column 159.5 at 0.4 m moves by
        // -0.05 * 300 / 0.4 = -37.5 px in colour; the far plane moves by -15 px.
        let row = &out[120 * w as usize..121 * w as usize];
        let edge_x = (159.5 - 0.05 * 300.0 / 0.4) as usize;
        assert_eq!(row[edge_x - 1], 400);
        assert_eq!(row[edge_x - 3], 400);
        // Between the near edge and where the far plane starts (159.5 - 15 =
        // 144.5): colour sees the far plane there, the depth sensor could not
        // (the near plane hid it): a hole, not a wrong value.
        assert!(
            row[edge_x + 2..144].iter().all(|z| *z == 0),
            "{:?}",
            &row[edge_x..150]
        );
        assert_eq!(row[146], 1000);
        // No far value ever lands on the near plane.
        assert!(row[..edge_x - 1].iter().all(|z| *z == 400 || *z == 0));
    }

    #[test]
    fn bad_sizes_and_distorted_depth_are_named() {
        let k = pinhole(8, 8, 10.0);
        let mut out = vec![0; 64];
        let e = align_to_colour(&[0; 10], &k, &k, &IDENTITY, 0.001, &mut out).unwrap_err();
        assert!(e.to_string().contains("10 depth values"), "{e}");
        let mut d = k;
        d.dist[0] = 0.1;
        let e = align_to_colour(&[0; 64], &d, &k, &IDENTITY, 0.001, &mut out).unwrap_err();
        assert!(e.to_string().contains("distortion"), "{e}");
    }
}
