//! Pre-fit consistency checks of a hand-eye data set: do the flange poses and the
//! board poses belong together, in the right conventions and units?
//!
//! A hand-eye fit always returns *some* transform. Quaternions written w, x, y, z,
//! a target size in millimetres written as metres, or flange poses from another
//! recording all give a confident, wrong number. These checks catch such input
//! before the fit, from invariants of `A X = X B` that hold whatever the hand-eye
//! `X` is, and say what the likely cause is.
//!
//! # The invariants
//!
//! For captures `i`, `j` the robot's relative motion
//! `A = base_from_flange[i]⁻¹ · base_from_flange[j]` and the camera's
//! `B = camera_from_target[i] · camera_from_target[j]⁻¹` are conjugate:
//! `A = X B X⁻¹`. So, for every pair:
//!
//! 1. their **rotation angles** are equal;
//! 2. their **pitches** (translation along the screw axis, `t · axis`) are equal:
//!    with `t_A = R_X t_B + t_X − R_A t_X` and `axis_A = R_X axis_B`, the `t_X` terms
//!    cancel because `R_Aᵀ axis_A = axis_A`. The pitch is a length, so it is
//!    scale-sensitive: a board 1000x too large shows as camera pitches 1000x the
//!    robot's.
//!
//! Note that the angle of a relative rotation is a function of the 4-D dot product of
//! the two unit quaternions alone, so it is blind to a permutation of quaternion
//! components: **w, x, y, z order never shows in the angles**, only in the pitches
//! (the screw axes and the frames of the translations change).
//!
//! What the invariants cannot see: flange poses given inverted (`flange_from_base`)
//! and eye-to-hand data. `B_i B_j⁻¹` is conjugate to the inverse of `B_i⁻¹ B_j`, and
//! a screw motion and its inverse have the same angle and pitch, so such data
//! satisfies both invariants (it is a valid `A X = X B` problem, of another set-up);
//! the fit's residuals have to show it.
//!
//! # Noise and decisions
//!
//! Each pair's disagreement is divided by its predicted standard deviation from
//! [`SanityNoise`] (robot and PnP noise, propagated through the pair's own angle,
//! axis and lever arms), giving a score in σ. The defaults are the upper ends of
//! real noise (robot 0.1° / 1 mm, PnP 0.3° / 2 mm + 3 % of the distance), so clean
//! data scores well below 1σ and the limit of [`SanityOptions::max_score`] (5σ)
//! leaves a wide margin.
//!
//! # Bounded work
//!
//! Up to [`MAX_PARTNERS`]` + 1` captures every pair is compared. Beyond, each
//! capture is compared with [`MAX_PARTNERS`] others chosen deterministically
//! ([`pair_indices`]: the captures `MAX_PARTNERS / 2` offsets ahead and behind,
//! the offsets spread from 1 to half the list, so near and far captures both
//! count), so time and memory grow linearly with the captures, not with their
//! square (all pairs of 3,000 rows took 21 s and 1.2 GB; of a million rows,
//! an allocation of 28 TB). A capture's median over 48 others still singles out
//! a typo row, as the median over all does.
//!
//! Every capture gets the median score of its pairs. A capture whose median exceeds
//! the limit disagrees with most others: it is listed in
//! [`SanityReport::suspects`] (a typo row, a pose recorded while the robot moved),
//! and the data set is still accepted. Only when the median over captures exceeds
//! the limit, i.e. most captures disagree, is the data set refused, with the first
//! explanation that fits:
//!
//! - angles disagree: [`CalibError::PosesDoNotBelong`] (wrong rows, another robot's
//!   poses, a different recording);
//! - angles agree, pitches agree after reading the flange (or board) quaternions as
//!   w, x, y, z: [`CalibError::QuaternionOrder`];
//! - pitches agree after dividing the camera side by one ratio far from 1:
//!   [`CalibError::ScaleMismatch`] with the ratio and its likely unit;
//! - otherwise [`CalibError::PosesDoNotBelong`] with the pitch numbers.
//!
//! Independently, a median board distance outside
//! [`SanityOptions::board_distance_m`] is refused as
//! [`CalibError::BoardDistanceImplausible`] (when the pitches are too small to
//! show a scale error, the distance still does).

use nalgebra::{UnitQuaternion, Vector3};

use crate::degeneracy::{check_finite, check_same_length};
use crate::metrics::median;
use crate::{CalibError, Iso3};

/// The noise the checks allow for: standard deviations per pose (per axis).
#[derive(Debug, Clone, PartialEq)]
pub struct SanityNoise {
    /// Robot flange orientation (rad). Default 0.1°: real arms' reported
    /// orientation is good to 0.01–0.1°.
    pub robot_rotation_rad: f64,
    /// Robot flange position (m). Default 1 mm: real arms 0.1–1 mm (the iiwa's
    /// repeatability is ±0.1 mm, its absolute accuracy worse).
    pub robot_translation_m: f64,
    /// Board orientation from PnP (rad). Default 0.3°: a board at half a metre in a
    /// VGA image with imperfect intrinsics.
    pub camera_rotation_rad: f64,
    /// Board position from PnP (m). Default 2 mm.
    pub camera_translation_m: f64,
    /// Relative scale error of board positions (focal length, printed size).
    /// Default 3 %.
    pub camera_scale_rel: f64,
}

impl Default for SanityNoise {
    fn default() -> Self {
        SanityNoise {
            robot_rotation_rad: 0.1_f64.to_radians(),
            robot_translation_m: 1e-3,
            camera_rotation_rad: 0.3_f64.to_radians(),
            camera_translation_m: 2e-3,
            camera_scale_rel: 0.03,
        }
    }
}

/// Options of [`check_pose_pairs`].
#[derive(Debug, Clone, PartialEq)]
pub struct SanityOptions {
    pub noise: SanityNoise,
    /// A disagreement above this many predicted standard deviations is not noise.
    /// Default 5.
    pub max_score: f64,
    /// Pitches are compared only for relative rotations in
    /// `[min_pitch_angle, π − min_pitch_angle]` on both sides: below, the screw axis
    /// is noise; near π its sign is. Default 5°.
    pub min_pitch_angle_rad: f64,
    /// Plausible median camera-to-board distances (m). Default 3 cm to 5 m: a
    /// flange camera in a robot cell.
    pub board_distance_m: (f64, f64),
    /// Fewest captures for any check (fewer: nothing is checked). Default 3.
    pub min_captures: usize,
    /// Fewest captures for listing individual suspects. Default 5 (each capture
    /// then has at least 4 pairs for its median).
    pub min_captures_for_suspects: usize,
}

impl Default for SanityOptions {
    fn default() -> Self {
        SanityOptions {
            noise: SanityNoise::default(),
            max_score: 5.0,
            min_pitch_angle_rad: 5f64.to_radians(),
            board_distance_m: (0.03, 5.0),
            min_captures: 3,
            min_captures_for_suspects: 5,
        }
    }
}

/// A capture whose motions disagree with most of the others.
#[derive(Debug, Clone, PartialEq)]
pub struct SuspectCapture {
    /// Index into the input lists.
    pub index: usize,
    /// Median over this capture's pairs of the larger of its two scores (σ).
    pub score: f64,
    /// Median rotation-angle difference of its pairs (rad).
    pub median_angle_diff_rad: f64,
    /// Median pitch difference of its pairs (m).
    pub median_pitch_diff_m: f64,
    /// Human-readable reason, for a rejected-capture entry.
    pub reason: String,
}

/// What [`check_pose_pairs`] measured on an accepted data set.
#[derive(Debug, Clone, PartialEq)]
pub struct SanityReport {
    pub captures: usize,
    /// Pairs compared (all `i < j` up to `MAX_PARTNERS + 1` captures, else
    /// `MAX_PARTNERS / 2` per capture: [`pair_indices`]).
    pub pairs: usize,
    /// Pairs whose pitches were compared.
    pub pitch_pairs: usize,
    /// Whether the checks ran (false below [`SanityOptions::min_captures`]).
    pub checked: bool,
    /// Median over captures of their median angle score (σ).
    pub angle_score: f64,
    /// Median over captures of their median pitch score (σ).
    pub pitch_score: f64,
    /// Median absolute rotation-angle difference over all pairs (rad).
    pub median_angle_diff_rad: f64,
    /// Median absolute pitch difference over the pitch pairs (m).
    pub median_pitch_diff_m: f64,
    /// Median camera-to-board distance (m).
    pub median_board_distance_m: f64,
    /// Captures that disagree with most others (to reject, with their reason).
    pub suspects: Vec<SuspectCapture>,
}

/// Most other captures one capture is compared with (module docs, "Bounded
/// work"); up to `MAX_PARTNERS + 1` captures, all pairs are compared.
pub const MAX_PARTNERS: usize = 48;

/// The pairs `(i, j)` of `n` captures that the checks compare: every `i < j`
/// up to `MAX_PARTNERS + 1` captures; beyond, each capture `i` with `i + s`
/// (modulo `n`) for `MAX_PARTNERS / 2` distinct offsets `s` spread over
/// `1 ..= (n - 1) / 2`, so each capture is in `MAX_PARTNERS` pairs and no pair
/// is listed twice. Deterministic: the same captures always give the same pairs.
pub fn pair_indices(n: usize) -> Vec<(usize, usize)> {
    if n <= MAX_PARTNERS + 1 {
        let mut out = Vec::with_capacity(n * n.saturating_sub(1) / 2);
        for i in 0..n {
            for j in (i + 1)..n {
                out.push((i, j));
            }
        }
        return out;
    }
    let m = MAX_PARTNERS / 2;
    // n >= 2m + 2, so span >= m - 1 and the offsets rise by at least 1; the
    // largest, (n - 1) / 2, is below n / 2, so no pair comes back reversed.
    let span = (n - 1) / 2 - 1;
    let offsets: Vec<usize> = (0..m).map(|k| 1 + k * span / (m - 1)).collect();
    let mut out = Vec::with_capacity(n * m);
    for i in 0..n {
        for s in &offsets {
            out.push((i, (i + s) % n));
        }
    }
    out
}

/// How many pairs [`pair_indices`] lists for `n` captures.
pub fn pair_count(n: usize) -> usize {
    if n <= MAX_PARTNERS + 1 {
        n * n.saturating_sub(1) / 2
    } else {
        n * (MAX_PARTNERS / 2)
    }
}

/// One relative motion: angle, unit axis, translation.
#[derive(Debug, Clone, Copy)]
struct Motion {
    angle: f64,
    axis: Vector3<f64>,
    t: Vector3<f64>,
}

impl Motion {
    fn of(m: &Iso3) -> Motion {
        let angle = m.rotation.angle();
        let axis = m
            .rotation
            .axis()
            .map(|a| a.into_inner())
            .unwrap_or_else(Vector3::zeros);
        Motion {
            angle,
            axis,
            t: m.translation.vector,
        }
    }

    fn pitch(&self) -> f64 {
        self.t.dot(&self.axis)
    }

    fn t_perp(&self) -> f64 {
        (self.t - self.axis * self.pitch()).norm()
    }
}

/// One side's noise as the pair computation needs it.
#[derive(Debug, Clone, Copy)]
struct SideNoise {
    rot: f64,
    trans: f64,
    scale_rel: f64,
}

/// Predicted standard deviation of one side's pitch; `lever` is the distance of
/// the poses' origins whose rotation error moves the relative translation.
fn pitch_sigma(m: &Motion, n: SideNoise, lever: f64) -> f64 {
    let rel_rot = std::f64::consts::SQRT_2 * n.rot;
    let sigma_axis = rel_rot / (2.0 * (m.angle / 2.0).sin()).max(1e-9);
    let t = m.t.norm();
    let st2 = 2.0 * n.trans * n.trans
        + n.rot * n.rot * (t * t + lever * lever)
        + (n.scale_rel * m.pitch()).powi(2);
    (st2 + (m.t_perp() * sigma_axis).powi(2)).sqrt()
}

/// One pair's comparison: (i, j, angle score, angle diff, pitch score and diff
/// when compared).
type PairRow = (usize, usize, f64, f64, Option<(f64, f64)>);

/// The per-pair comparison of one hypothesis about the data.
#[derive(Debug, Clone)]
struct PairTable {
    n: usize,
    pairs: Vec<PairRow>,
}

impl PairTable {
    fn build(
        base_from_flange: &[Iso3],
        camera_from_target: &[Iso3],
        o: &SanityOptions,
        camera_scale: f64,
    ) -> PairTable {
        let n = base_from_flange.len();
        let nz = &o.noise;
        let robot = SideNoise {
            rot: nz.robot_rotation_rad,
            trans: nz.robot_translation_m,
            scale_rel: 0.0,
        };
        let camera = SideNoise {
            rot: nz.camera_rotation_rad,
            // In the rescaled units the noise is the nominal one.
            trans: nz.camera_translation_m,
            scale_rel: nz.camera_scale_rel,
        };
        let sigma_angle = (2.0 * (robot.rot.powi(2) + camera.rot.powi(2))).sqrt();
        let lo = o.min_pitch_angle_rad;
        let hi = std::f64::consts::PI - o.min_pitch_angle_rad;
        let indices = pair_indices(n);
        let mut pairs = Vec::with_capacity(indices.len());
        {
            for (i, j) in indices {
                let a = Motion::of(&(base_from_flange[i].inverse() * base_from_flange[j]));
                let mut b_iso = camera_from_target[i] * camera_from_target[j].inverse();
                b_iso.translation.vector /= camera_scale;
                let b = Motion::of(&b_iso);
                let da = (a.angle - b.angle).abs();
                let pitch = (a.angle >= lo && a.angle <= hi && b.angle >= lo && b.angle <= hi)
                    .then(|| {
                        let lever = 0.5
                            * (camera_from_target[i].translation.vector.norm()
                                + camera_from_target[j].translation.vector.norm())
                            / camera_scale;
                        let s = (pitch_sigma(&a, robot, 0.0).powi(2)
                            + pitch_sigma(&b, camera, lever).powi(2))
                        .sqrt();
                        let dp = (a.pitch() - b.pitch()).abs();
                        (dp / s, dp)
                    });
                pairs.push((i, j, da / sigma_angle, da, pitch));
            }
        }
        PairTable { n, pairs }
    }

    /// Per capture: (median angle score, median pitch score, median combined score,
    /// median angle diff, median pitch diff).
    fn per_capture(&self) -> Vec<[f64; 5]> {
        let mut acc: Vec<[Vec<f64>; 5]> = (0..self.n).map(|_| Default::default()).collect();
        for &(i, j, sa, da, p) in &self.pairs {
            for k in [i, j] {
                acc[k][0].push(sa);
                acc[k][3].push(da);
                match p {
                    Some((sp, dp)) => {
                        acc[k][1].push(sp);
                        acc[k][2].push(sa.max(sp));
                        acc[k][4].push(dp);
                    }
                    None => acc[k][2].push(sa),
                }
            }
        }
        acc.into_iter()
            .map(|mut a| {
                [
                    median(&mut a[0]),
                    median(&mut a[1]),
                    median(&mut a[2]),
                    median(&mut a[3]),
                    median(&mut a[4]),
                ]
            })
            .collect()
    }

    /// (median over captures of angle scores, of pitch scores).
    fn scores(&self) -> (f64, f64) {
        let per = self.per_capture();
        let mut a: Vec<f64> = per.iter().map(|p| p[0]).collect();
        let mut p: Vec<f64> = per.iter().map(|p| p[1]).collect();
        (median(&mut a), median(&mut p))
    }
}

/// Reads every rotation's quaternion as if its stored (x, y, z, w) were (w, x, y, z).
fn reread_wxyz(poses: &[Iso3]) -> Vec<Iso3> {
    poses
        .iter()
        .map(|p| {
            let c = p.rotation.coords; // nalgebra stores [i, j, k, w]
            let q = nalgebra::Quaternion::new(c[0], c[1], c[2], c[3]);
            Iso3::from_parts(p.translation, UnitQuaternion::new_normalize(q))
        })
        .collect()
}

/// The ratio camera/robot of the pitches, weighted by the robot side's precision,
/// over pairs whose robot pitch is clearly non-zero (all pairs if none is).
fn pitch_ratio(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    o: &SanityOptions,
) -> Option<f64> {
    let n = base_from_flange.len();
    let robot = SideNoise {
        rot: o.noise.robot_rotation_rad,
        trans: o.noise.robot_translation_m,
        scale_rel: 0.0,
    };
    let lo = o.min_pitch_angle_rad;
    let hi = std::f64::consts::PI - lo;
    let mut ratios = Vec::new();
    let (mut sab, mut saa) = (0.0, 0.0);
    {
        for (i, j) in pair_indices(n) {
            let a = Motion::of(&(base_from_flange[i].inverse() * base_from_flange[j]));
            let b = Motion::of(&(camera_from_target[i] * camera_from_target[j].inverse()));
            if !(a.angle >= lo && a.angle <= hi && b.angle >= lo && b.angle <= hi) {
                continue;
            }
            let s = pitch_sigma(&a, robot, 0.0);
            let w = 1.0 / (s * s);
            sab += w * a.pitch() * b.pitch();
            saa += w * a.pitch() * a.pitch();
            if a.pitch().abs() > 5.0 * s {
                ratios.push(b.pitch() / a.pitch());
            }
        }
    }
    if ratios.len() >= 3 {
        Some(median(&mut ratios))
    } else if saa > 0.0 {
        Some(sab / saa)
    } else {
        None
    }
}

/// The likely cause of a camera/robot length ratio.
pub fn scale_hint(ratio: f64) -> &'static str {
    const HINTS: [(f64, &str); 8] = [
        (
            1000.0,
            "a length in millimetres written as metres? check the target's square_m / marker_m",
        ),
        (
            1e-3,
            "the target's dimensions 1000x too small, or robot positions in millimetres?",
        ),
        (
            25.4,
            "inches and millimetres mixed up in the target's dimensions?",
        ),
        (
            1.0 / 25.4,
            "inches and millimetres mixed up in the target's dimensions?",
        ),
        (
            100.0,
            "a length in centimetres written as metres? check the target's dimensions",
        ),
        (
            0.01,
            "the target's dimensions 100x too small (metres written where centimetres were meant)?",
        ),
        (
            10.0,
            "millimetres and centimetres mixed up in the target's dimensions?",
        ),
        (
            0.1,
            "millimetres and centimetres mixed up in the target's dimensions?",
        ),
    ];
    let r = ratio.abs();
    HINTS
        .iter()
        .filter(|(k, _)| (r / k).ln().abs() < 0.25_f64)
        .map(|(_, h)| *h)
        .next()
        .unwrap_or("check the target's dimensions (square_m, marker_m) and the camera intrinsics")
}

/// Checks that flange poses and board poses belong together (module docs). On
/// success returns what was measured, with the captures that disagree with most
/// others in [`SanityReport::suspects`]; on a data-set-wide disagreement returns
/// the named error of the first explanation that fits.
pub fn check_pose_pairs(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    o: &SanityOptions,
) -> Result<SanityReport, CalibError> {
    check_same_length(base_from_flange, camera_from_target)?;
    check_finite(base_from_flange, "base_from_flange")?;
    check_finite(camera_from_target, "camera_from_target")?;
    let n = base_from_flange.len();
    let mut dist: Vec<f64> = camera_from_target
        .iter()
        .map(|c| c.translation.vector.norm())
        .collect();
    let median_board_distance_m = median(&mut dist);
    let mut report = SanityReport {
        captures: n,
        pairs: pair_count(n),
        pitch_pairs: 0,
        checked: false,
        angle_score: 0.0,
        pitch_score: 0.0,
        median_angle_diff_rad: 0.0,
        median_pitch_diff_m: 0.0,
        median_board_distance_m,
        suspects: vec![],
    };
    if n < o.min_captures.max(3) {
        return Ok(report);
    }
    report.checked = true;
    let table = PairTable::build(base_from_flange, camera_from_target, o, 1.0);
    let (angle_score, pitch_score) = table.scores();
    let mut da: Vec<f64> = table.pairs.iter().map(|p| p.3).collect();
    let mut dp: Vec<f64> = table
        .pairs
        .iter()
        .filter_map(|p| p.4.map(|x| x.1))
        .collect();
    report.pitch_pairs = dp.len();
    report.angle_score = angle_score;
    report.pitch_score = pitch_score;
    report.median_angle_diff_rad = median(&mut da);
    report.median_pitch_diff_m = median(&mut dp);
    let limit = o.max_score;

    if angle_score > limit {
        return Err(CalibError::PosesDoNotBelong {
            what: "rotation angles",
            median_diff: format!("{:.2} deg", report.median_angle_diff_rad.to_degrees()),
            score: angle_score,
            limit,
            pairs: report.pairs,
        });
    }
    let (lo_d, hi_d) = o.board_distance_m;
    let distance_ok = median_board_distance_m >= lo_d && median_board_distance_m <= hi_d;
    if pitch_score > limit || !distance_ok {
        // Which reading of the data makes the pitches agree?
        let fits = |b: &[Iso3], c: &[Iso3], scale: f64| {
            PairTable::build(b, c, o, scale).scores().1 <= limit
        };
        let ratio = pitch_ratio(base_from_flange, camera_from_target, o);
        if pitch_score > limit {
            let robot_wxyz = reread_wxyz(base_from_flange);
            let camera_wxyz = reread_wxyz(camera_from_target);
            let score_of = |b: &[Iso3], c: &[Iso3]| PairTable::build(b, c, o, 1.0).scores().1;
            if fits(&robot_wxyz, camera_from_target, 1.0) {
                return Err(CalibError::QuaternionOrder {
                    poses: "flange poses (base_from_flange)",
                    score: pitch_score,
                    reread_score: score_of(&robot_wxyz, camera_from_target),
                    median_pitch_diff_m: report.median_pitch_diff_m,
                });
            }
            if fits(base_from_flange, &camera_wxyz, 1.0) {
                return Err(CalibError::QuaternionOrder {
                    poses: "board poses (camera_from_target)",
                    score: pitch_score,
                    reread_score: score_of(base_from_flange, &camera_wxyz),
                    median_pitch_diff_m: report.median_pitch_diff_m,
                });
            }
        }
        if let Some(r) = ratio
            && r.is_finite()
            && r.abs().ln().abs() > 1.5_f64.ln()
            && (fits(base_from_flange, camera_from_target, r) || !distance_ok)
        {
            return Err(CalibError::ScaleMismatch {
                ratio: r,
                median_board_distance_m,
                pitch_pairs: report.pitch_pairs,
                hint: scale_hint(r),
            });
        }
        if !distance_ok {
            return Err(CalibError::BoardDistanceImplausible {
                median_m: median_board_distance_m,
                min_m: lo_d,
                max_m: hi_d,
            });
        }
        return Err(CalibError::PosesDoNotBelong {
            what: "pitches (translation along the screw axis)",
            median_diff: format!("{:.1} mm", report.median_pitch_diff_m * 1e3),
            score: pitch_score,
            limit,
            pairs: report.pitch_pairs,
        });
    }

    if n >= o.min_captures_for_suspects {
        for (index, p) in table.per_capture().into_iter().enumerate() {
            if p[2] > limit {
                report.suspects.push(SuspectCapture {
                    index,
                    score: p[2],
                    median_angle_diff_rad: p[3],
                    median_pitch_diff_m: p[4],
                    reason: format!(
                        "its motions to the other captures disagree between robot and camera \
                         (median {:.1} sigma: rotation angle {:.2} deg, pitch {:.1} mm); \
                         a typo in the row or a pose recorded while the robot moved?",
                        p[2],
                        p[3].to_degrees(),
                        p[4] * 1e3
                    ),
                });
            }
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{SynthConfig, SynthRobot, random_robot, two_robots};
    use nalgebra::Quaternion;

    fn robot(seed: u64, captures: usize, robot_t: f64, robot_r_deg: f64, px: f64) -> SynthRobot {
        let cfg = SynthConfig {
            captures,
            robot_sigma_t: robot_t,
            robot_sigma_r: robot_r_deg.to_radians(),
            pixel_sigma: px,
            ..SynthConfig::default()
        };
        random_robot(seed, &cfg).unwrap()
    }

    fn check(b: &[Iso3], c: &[Iso3]) -> Result<SanityReport, CalibError> {
        check_pose_pairs(b, c, &SanityOptions::default())
    }

    /// Clean data passes with no suspects, at the simulator's default noise, at 5x the
    /// iiwa's repeatability (±0.1 mm, so 0.5 mm and 0.05°) with 0.5 px corners, and at
    /// the upper end of real robots (1 mm, 0.1°, 1 px).
    #[test]
    fn clean_data_passes_at_several_noise_levels() {
        let levels = [
            ("sim default", 0.05e-3, 0.01, 0.2),
            ("5x iiwa repeatability", 0.5e-3, 0.05, 0.5),
            ("1 mm / 0.1 deg / 1 px", 1e-3, 0.1, 1.0),
        ];
        for (name, t, r, px) in levels {
            let mut worst: f64 = 0.0;
            for seed in 0..6 {
                let s = robot(seed, 20, t, r, px);
                let rep = check(&s.base_from_flange, &s.camera_from_target)
                    .unwrap_or_else(|e| panic!("{name}, seed {seed}: {e}"));
                assert!(rep.checked && rep.pitch_pairs > 50, "{rep:?}");
                assert!(rep.suspects.is_empty(), "{name}, seed {seed}: {rep:?}");
                worst = worst.max(rep.angle_score).max(rep.pitch_score);
                if seed == 0 {
                    eprintln!(
                        "{name}: angle score {:.2} sigma (median diff {:.4} deg), pitch score {:.2} sigma (median diff {:.3} mm), board at {:.2} m",
                        rep.angle_score,
                        rep.median_angle_diff_rad.to_degrees(),
                        rep.pitch_score,
                        rep.median_pitch_diff_m * 1e3,
                        rep.median_board_distance_m
                    );
                }
            }
            eprintln!("{name}: worst median score over 6 seeds {worst:.2} sigma");
            assert!(worst < 2.0, "{name}: {worst}");
        }
    }

    /// The quaternion columns hold w, x, y, z but are read as x, y, z, w.
    fn written_wxyz(poses: &[Iso3]) -> Vec<Iso3> {
        poses
            .iter()
            .map(|p| {
                let q = p.rotation.quaternion();
                // Columns qx, qy, qz, qw hold w, x, y, z.
                let (qx, qy, qz, qw) = (q.w, q.i, q.j, q.k);
                let read = Quaternion::new(qw, qx, qy, qz);
                Iso3::from_parts(p.translation, UnitQuaternion::from_quaternion(read))
            })
            .collect()
    }

    #[test]
    fn wxyz_quaternions_are_named() {
        for seed in 0..4 {
            let s = robot(seed, 12, 0.2e-3, 0.02, 0.3);
            let bad = written_wxyz(&s.base_from_flange);
            let err = check(&bad, &s.camera_from_target).unwrap_err();
            eprintln!("seed {seed}: {err}");
            assert!(
                matches!(err, CalibError::QuaternionOrder { poses, .. } if poses.starts_with("flange")),
                "{err:?}"
            );
            assert!(err.to_string().contains("w, x, y, z"));
            // Board poses given w, x, y, z (pose-only rows) are named as such.
            let bad = written_wxyz(&s.camera_from_target);
            let err = check(&s.base_from_flange, &bad).unwrap_err();
            assert!(
                matches!(err, CalibError::QuaternionOrder { poses, .. } if poses.starts_with("board")),
                "{err:?}"
            );
        }
    }

    /// A target size in millimetres written as metres scales every board position
    /// by 1000; inches and 1000x too small are told apart by the estimated ratio.
    #[test]
    fn scale_errors_are_named_with_the_ratio() {
        for (factor, words) in [
            (1000.0, "millimetres written as metres"),
            (25.4, "inches"),
            (1e-3, "1000x too small"),
            (10.0, "centimetres"),
        ] {
            for seed in 0..3 {
                let s = robot(seed, 12, 0.2e-3, 0.02, 0.3);
                let scaled: Vec<Iso3> = s
                    .camera_from_target
                    .iter()
                    .map(|c| {
                        let mut c = *c;
                        c.translation.vector *= factor;
                        c
                    })
                    .collect();
                let err = check(&s.base_from_flange, &scaled).unwrap_err();
                eprintln!("x{factor}, seed {seed}: {err}");
                let CalibError::ScaleMismatch { ratio, .. } = err else {
                    panic!("x{factor}: {err:?}");
                };
                assert!(
                    (ratio / factor - 1.0).abs() < 0.05,
                    "x{factor}: ratio {ratio}"
                );
                assert!(err.to_string().contains(words), "{err}");
            }
        }
    }

    /// Flange poses paired with the wrong board poses (rows shifted, or the other
    /// robot's poses) are refused as not belonging together.
    #[test]
    fn mismatched_rows_are_refused() {
        let s = robot(3, 12, 0.2e-3, 0.02, 0.3);
        let mut shifted = s.camera_from_target.clone();
        shifted.rotate_left(3);
        let err = check(&s.base_from_flange, &shifted).unwrap_err();
        eprintln!("rows shifted by 3: {err}");
        assert!(
            matches!(err, CalibError::PosesDoNotBelong { what, .. } if what == "rotation angles"),
            "{err:?}"
        );
        assert!(err.to_string().contains("do not belong together"));

        let two = two_robots(
            5,
            &SynthConfig {
                captures: 12,
                ..SynthConfig::default()
            },
        )
        .unwrap();
        let err = check(
            &two.robots[0].base_from_flange,
            &two.robots[1].camera_from_target,
        )
        .unwrap_err();
        eprintln!("robot 1 flange with robot 2 board poses: {err}");
        assert!(
            matches!(err, CalibError::PosesDoNotBelong { .. }),
            "{err:?}"
        );
    }

    /// One row with tx off by 65 cm, or two gross rows, do not fail the data set:
    /// they are listed as suspects and nothing else is.
    #[test]
    fn gross_rows_are_listed_not_fatal() {
        for seed in 0..4 {
            let s = robot(seed, 12, 0.2e-3, 0.02, 0.3);
            let mut b = s.base_from_flange.clone();
            b[4].translation.vector.x += 0.65;
            let rep = check(&b, &s.camera_from_target).unwrap();
            let idx: Vec<usize> = rep.suspects.iter().map(|x| x.index).collect();
            eprintln!(
                "seed {seed}: one 65 cm typo: suspects {idx:?} ({})",
                rep.suspects
                    .first()
                    .map(|x| x.reason.as_str())
                    .unwrap_or("-")
            );
            assert_eq!(idx, vec![4]);

            // A second gross row: a wrong orientation (30 deg off).
            b[9].rotation =
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.5) * b[9].rotation;
            let rep = check(&b, &s.camera_from_target).unwrap();
            let idx: Vec<usize> = rep.suspects.iter().map(|x| x.index).collect();
            eprintln!("seed {seed}: plus one 30 deg row: suspects {idx:?}");
            assert_eq!(idx, vec![4, 9]);
        }
    }

    /// Beyond `MAX_PARTNERS + 1` captures each capture is in `MAX_PARTNERS`
    /// distinct pairs (no pair twice, none with itself); up to it, all pairs.
    #[test]
    fn pairs_are_bounded_per_capture() {
        for n in [0, 1, 2, 5, MAX_PARTNERS + 1] {
            assert_eq!(pair_indices(n).len(), n * n.saturating_sub(1) / 2);
            assert_eq!(pair_count(n), pair_indices(n).len());
        }
        for n in [MAX_PARTNERS + 2, MAX_PARTNERS + 3, 100, 101, 3000] {
            let pairs = pair_indices(n);
            assert_eq!(pairs.len(), pair_count(n));
            let mut per = vec![0usize; n];
            let mut seen = std::collections::HashSet::new();
            for &(i, j) in &pairs {
                assert_ne!(i, j);
                assert!(seen.insert((i.min(j), i.max(j))), "n {n}: ({i}, {j}) twice");
                per[i] += 1;
                per[j] += 1;
            }
            assert!(per.iter().all(|&k| k == MAX_PARTNERS), "n {n}");
            // Near and far partners both.
            let far = pairs
                .iter()
                .map(|&(i, j)| j.abs_diff(i).min(n - j.abs_diff(i)))
                .max();
            assert_eq!(far, Some((n - 1) / 2), "n {n}");
        }
    }

    /// A typo row among 3,000 captures is still found, with the work bounded:
    /// 48 partners per capture (72,000 pairs, not 4.5 million).
    #[test]
    fn a_typo_row_among_thousands_is_found_with_bounded_pairs() {
        let s = robot(7, 3000, 0.2e-3, 0.02, 0.3);
        let mut b = s.base_from_flange.clone();
        b[1234].translation.vector.x += 0.65;
        let rep = check(&b, &s.camera_from_target).unwrap();
        assert_eq!(rep.pairs, 3000 * MAX_PARTNERS / 2);
        let idx: Vec<usize> = rep.suspects.iter().map(|x| x.index).collect();
        assert_eq!(idx, vec![1234], "{rep:?}");
    }

    #[test]
    fn too_few_captures_are_not_checked() {
        let s = robot(1, 12, 0.2e-3, 0.02, 0.3);
        let rep = check(&s.base_from_flange[..2], &s.camera_from_target[..2]).unwrap();
        assert!(!rep.checked);
        assert!(check(&s.base_from_flange[..3], &s.camera_from_target[..2]).is_err());
    }
}
