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
//! Speed: per depth row, the patches are computed in one branch-free pass (f32,
//! vectorised) and then written; the rows are shared among up to four threads,
//! each writing its own band of colour rows (writes across a band's edge wait
//! for the join; the z-test is a minimum, so the image does not depend on the
//! number of threads).
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
    let bands = std::thread::available_parallelism().map_or(1, |n| n.get().min(MAX_BANDS));
    splat_in_bands(
        depth,
        depth_stream,
        colour_stream,
        colour_from_depth,
        unit_m,
        out,
        bands,
    );
    Ok(())
}

/// At most this many threads align one frame.
const MAX_BANDS: usize = 4;

/// The per-frame constants of the splat: per depth-pixel edge, its ray's part
/// in the colour frame.
struct Splat<'a> {
    depth: &'a [u16],
    dw: usize,
    cw: usize,
    ch: usize,
    colour: &'a FrameHeader,
    distorted: bool,
    t: [f64; 3],
    unit_m: f64,
    xs: Vec<[f64; 3]>,
    ys: Vec<[f64; 3]>,
    /// The same in f32, the columns' split by component (for vectorising).
    xs32: [Vec<f32>; 3],
    ys32: Vec<[f32; 3]>,
}

/// The part of the colour image one thread writes: rows `first..first + n`.
struct Band<'a> {
    first: usize,
    out: &'a mut [u16],
}

/// Splats depth rows in `bands` threads. Band `i` takes a share of the depth
/// rows and writes the colour rows their middle maps onto at 1 m; a write
/// outside a thread's own rows (parallax, a rotated extrinsic) is kept and
/// applied after the threads join. The z-test (0 = none, else the nearest) is
/// a minimum, so the order of writes does not matter: any number of bands
/// gives the same image.
fn splat_in_bands(
    depth: &[u16],
    d: &FrameHeader,
    c: &FrameHeader,
    colour_from_depth: &Extrinsic,
    unit_m: f64,
    out: &mut [u16],
    bands: usize,
) {
    let (dw, dh) = (d.width as usize, d.height as usize);
    let (cw, ch) = (c.width as usize, c.height as usize);
    let r = &colour_from_depth.rotation;
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
    let splat = Splat {
        depth,
        dw,
        cw,
        ch,
        colour: c,
        distorted: c.dist.iter().any(|k| *k != 0.0),
        t: colour_from_depth.translation_m,
        unit_m,
        xs32: [0, 1, 2].map(|k| xs.iter().map(|x| x[k] as f32).collect()),
        ys32: ys.iter().map(|y| y.map(|x| x as f32)).collect(),
        xs,
        ys,
    };
    out.fill(0);
    let bands = bands.clamp(1, dh.max(1));
    if bands == 1 {
        let mut spill = Vec::new();
        splat.rows(0..dh, Band { first: 0, out }, &mut spill);
        return;
    }
    // Band i: depth rows [dh i / n, dh (i+1) / n); colour rows from where the
    // first of them lands at 1 m, in the middle column (monotone, clamped).
    let depth_rows = |i: usize| dh * i / bands;
    let mut colour_rows: Vec<usize> = (0..=bands)
        .map(|i| match i {
            0 => 0,
            i if i == bands => ch,
            i => {
                let q = splat.corner(1.0, dw / 2, depth_rows(i));
                splat.project(q).map_or(ch * i / bands, |p| {
                    p[1].round().clamp(0.0, ch as f64) as usize
                })
            }
        })
        .collect();
    for i in 1..=bands {
        colour_rows[i] = colour_rows[i].max(colour_rows[i - 1]);
    }
    let mut spills: Vec<Vec<(usize, u16)>> = vec![Vec::new(); bands];
    std::thread::scope(|scope| {
        let mut rest = &mut out[..];
        let splat = &splat;
        for (i, spill) in spills.iter_mut().enumerate() {
            let (mine, later) = rest.split_at_mut((colour_rows[i + 1] - colour_rows[i]) * cw);
            rest = later;
            let band = Band {
                first: colour_rows[i],
                out: mine,
            };
            let rows = depth_rows(i)..depth_rows(i + 1);
            scope.spawn(move || splat.rows(rows, band, spill));
        }
    });
    for (k, z) in spills.into_iter().flatten() {
        out[k] = nearer(out[k], z);
    }
}

/// The z-test: 0 is no depth, otherwise the nearer wins (branch-free: 0 wraps
/// to the largest value).
fn nearer(old: u16, new: u16) -> u16 {
    old.wrapping_sub(1).min(new - 1) + 1
}

impl Splat<'_> {
    /// Depth pixel corner `(u, v)` (of pixel `(u, v)`'s top left, in the
    /// tables' indexing) at depth `z` (m), in the colour frame.
    fn corner(&self, z: f64, u: usize, v: usize) -> [f64; 3] {
        let (x, y, t) = (self.xs[u], self.ys[v], self.t);
        [
            z * (x[0] + y[0]) + t[0],
            z * (x[1] + y[1]) + t[1],
            z * (x[2] + y[2]) + t[2],
        ]
    }

    fn project(&self, q: [f64; 3]) -> Option<[f64; 2]> {
        let c = self.colour;
        if self.distorted {
            return project(c, q);
        }
        if q[2] <= 0.0 {
            return None;
        }
        let w = 1.0 / q[2];
        Some([c.fx * q[0] * w + c.cx, c.fy * q[1] * w + c.cy])
    }

    /// Each pixel of depth row `v`: the colour-image box its patch spans and
    /// its depth in the colour frame (in depth units; 0: it lands nowhere).
    /// Undistorted colour (a D4xx's factory model) takes a branch-free pass in
    /// f32, which the compiler vectorises (f32 is exact to 1e-4 px at this
    /// size); distorted colour goes pixel by pixel in f64.
    fn patches(&self, v: usize, p: &mut Patches) {
        let row = &self.depth[v * self.dw..(v + 1) * self.dw];
        if self.distorted {
            for (u, raw) in row.iter().enumerate() {
                let z = f64::from(*raw) * self.unit_m;
                let (qa, qb) = (self.corner(z, u, v), self.corner(z, u + 1, v + 1));
                let (a, b) = match (self.project(qa), self.project(qb)) {
                    (Some(a), Some(b)) if *raw > 0 => (a, b),
                    _ => ([0.0; 2], [0.0; 2]),
                };
                p.u_lo[u] = a[0].min(b[0]) as f32;
                p.u_hi[u] = a[0].max(b[0]) as f32;
                p.v_lo[u] = a[1].min(b[1]) as f32;
                p.v_hi[u] = a[1].max(b[1]) as f32;
                p.z[u] = if *raw > 0 && qa[2] > 0.0 && qb[2] > 0.0 {
                    (0.5 * (qa[2] + qb[2]) / self.unit_m) as f32
                } else {
                    0.0
                };
            }
            return;
        }
        let c = self.colour;
        let (fx, fy, cx, cy) = (c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32);
        let unit = self.unit_m as f32;
        let half_per_unit = (0.5 / self.unit_m) as f32;
        let t = self.t.map(|x| x as f32);
        let (ya, yb) = (self.ys32[v], self.ys32[v + 1]);
        let n = self.dw;
        let [x0, x1, x2] = &self.xs32;
        let (xa0, xa1, xa2) = (&x0[..n], &x1[..n], &x2[..n]);
        let (xb0, xb1, xb2) = (&x0[1..=n], &x1[1..=n], &x2[1..=n]);
        let (u_lo, u_hi) = (&mut p.u_lo[..n], &mut p.u_hi[..n]);
        let (v_lo, v_hi, zs) = (&mut p.v_lo[..n], &mut p.v_hi[..n], &mut p.z[..n]);
        for u in 0..n {
            let z = f32::from(row[u]) * unit;
            let qa = [
                z * (xa0[u] + ya[0]) + t[0],
                z * (xa1[u] + ya[1]) + t[1],
                z * (xa2[u] + ya[2]) + t[2],
            ];
            let qb = [
                z * (xb0[u] + yb[0]) + t[0],
                z * (xb1[u] + yb[1]) + t[1],
                z * (xb2[u] + yb[2]) + t[2],
            ];
            let (wa, wb) = (1.0 / qa[2], 1.0 / qb[2]);
            let (au, av) = (fx * qa[0] * wa + cx, fy * qa[1] * wa + cy);
            let (bu, bv) = (fx * qb[0] * wb + cx, fy * qb[1] * wb + cy);
            u_lo[u] = if au < bu { au } else { bu };
            u_hi[u] = if au < bu { bu } else { au };
            v_lo[u] = if av < bv { av } else { bv };
            v_hi[u] = if av < bv { bv } else { av };
            // No depth, or behind the colour camera: nowhere.
            let visible = z > 0.0 && qa[2] > 0.0 && qb[2] > 0.0;
            zs[u] = if visible {
                (qa[2] + qb[2]) * half_per_unit
            } else {
                0.0
            };
        }
    }

    /// Splats depth `rows` into `band`; writes that fall outside it go to
    /// `spill` as (index in the whole image, depth).
    fn rows(&self, rows: std::ops::Range<usize>, band: Band<'_>, spill: &mut Vec<(usize, u16)>) {
        let cw = self.cw;
        let (last_u, last_v) = (cw as i32 - 1, self.ch as i32 - 1);
        let band_rows = band.first..band.first + band.out.len() / cw.max(1);
        let mut p = Patches::new(self.dw);
        for v in rows {
            self.patches(v, &mut p);
            p.spans(last_u, last_v);
            for u in 0..self.dw {
                let zc = p.depth[u];
                let (u0, u1, v0, v1) = (p.u0[u], p.u1[u], p.v0[u], p.v1[u]);
                if zc == 0 || u0 > u1 || v0 > v1 {
                    continue;
                }
                let (u0, u1) = (u0 as usize, u1 as usize);
                for y in v0 as usize..=v1 as usize {
                    if band_rows.contains(&y) {
                        let row = (y - band.first) * cw;
                        for px in &mut band.out[row + u0..=row + u1] {
                            *px = nearer(*px, zc);
                        }
                    } else {
                        spill.extend((u0..=u1).map(|x| (y * cw + x, zc)));
                    }
                }
            }
        }
    }
}

/// One depth row's patches in the colour image: the box each spans (pixels)
/// and its depth there (depth units; 0: none).
struct Patches {
    u_lo: Vec<f32>,
    u_hi: Vec<f32>,
    v_lo: Vec<f32>,
    v_hi: Vec<f32>,
    z: Vec<f32>,
    /// From those ([`Patches::spans`]): the colour pixels covered, and depth
    /// in units.
    u0: Vec<i32>,
    u1: Vec<i32>,
    v0: Vec<i32>,
    v1: Vec<i32>,
    depth: Vec<u16>,
}

impl Patches {
    fn new(n: usize) -> Patches {
        Patches {
            u_lo: vec![0.0; n],
            u_hi: vec![0.0; n],
            v_lo: vec![0.0; n],
            v_hi: vec![0.0; n],
            z: vec![0.0; n],
            u0: vec![0; n],
            u1: vec![0; n],
            v0: vec![0; n],
            v1: vec![0; n],
            depth: vec![0; n],
        }
    }

    /// The colour pixels each patch covers: those whose centres it spans
    /// (along an axis it spans none of, the one holding its centre), clipped
    /// to the image (`last_u`, `last_v`: the last column and row); and its
    /// depth rounded to a unit (0: none or out of range). Branch-free, so
    /// vectorised.
    fn spans(&mut self, last_u: i32, last_v: i32) {
        let n = self.z.len();
        let (u_lo, u_hi, v_lo, v_hi) = (
            &self.u_lo[..n],
            &self.u_hi[..n],
            &self.v_lo[..n],
            &self.v_hi[..n],
        );
        let (u0, u1, v0, v1) = (
            &mut self.u0[..n],
            &mut self.u1[..n],
            &mut self.v0[..n],
            &mut self.v1[..n],
        );
        let (z, depth) = (&self.z[..n], &mut self.depth[..n]);
        for k in 0..n {
            (u0[k], u1[k]) = span(u_lo[k], u_hi[k], last_u);
            (v0[k], v1[k]) = span(v_lo[k], v_hi[k], last_v);
            let ok = z[k] >= 1.0 && z[k] < 65535.5;
            // Positive: +0.5 and truncation round it.
            depth[k] = if ok { (z[k] + 0.5) as u16 } else { 0 };
        }
    }
}

/// The pixel centres in `[lo, hi]`, or the one nearest its middle when there
/// are none, clipped to `0..=last` (empty when outside).
fn span(lo: f32, hi: f32, last: i32) -> (i32, i32) {
    let (a, b) = (ceil_i(lo), floor_i(hi));
    let mid = floor_i(0.5 * (lo + hi) + 0.5);
    let (a, b) = if a > b { (mid, mid) } else { (a, b) };
    (a.max(0), b.min(last))
}

/// `floor` and `ceil` to integers by truncation (no libm call, and
/// vectorised). Values outside `i32` saturate, NaN gives 0 (its depth is 0).
fn floor_i(x: f32) -> i32 {
    let t = x as i32;
    t - i32::from((t as f32) > x)
}

fn ceil_i(x: f32) -> i32 {
    let t = x as i32;
    t + i32::from((t as f32) < x)
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
    fn any_number_of_threads_gives_the_same_image() {
        // A turned extrinsic with a vertical offset and a near box: patches
        // cross the bands' seams both ways (parallax, rotation), and distortion.
        let d = pinhole(160, 120, 150.0);
        let c = FrameHeader::new(crate::StreamKind::Rgb8, 256, 144).with_intrinsics(
            230.0,
            231.0,
            127.0,
            70.0,
            [0.05, -0.02, 0.001, -0.001, 0.0],
        );
        let (a, b) = (0.04f64, -0.03f64);
        let e = Extrinsic {
            // Rx(a) Ry(b), row-major.
            rotation: [
                b.cos(),
                0.0,
                b.sin(),
                a.sin() * b.sin(),
                a.cos(),
                -a.sin() * b.cos(),
                -a.cos() * b.sin(),
                a.sin(),
                a.cos() * b.cos(),
            ],
            translation_m: [0.015, -0.03, 0.002],
        };
        let depth: Vec<u16> = (0..160 * 120)
            .map(|i| {
                let (u, v) = (i % 160, i / 160);
                if (40..110).contains(&u) && (50..75).contains(&v) {
                    250
                } else if u % 17 == 3 {
                    0
                } else {
                    600 + (v as u16) * 2
                }
            })
            .collect();
        let serial = {
            let mut out = vec![0; 256 * 144];
            splat_in_bands(&depth, &d, &c, &e, 0.001, &mut out, 1);
            out
        };
        assert!(serial.iter().filter(|z| **z > 0).count() > 256 * 144 / 2);
        for bands in [2, 3, 4, 7] {
            let mut out = vec![7; 256 * 144];
            splat_in_bands(&depth, &d, &c, &e, 0.001, &mut out, bands);
            assert!(out == serial, "{bands} bands differ from one");
        }
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
