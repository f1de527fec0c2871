//! Targets that look the same after a turn, and how robot motion decides their labelling.
//!
//! A checkerboard with odd x odd squares (8x6 inner corners) looks the same turned by
//! 180° about its centre, and a square one may also look the same turned by 90°: one
//! image cannot decide which corner is which, so a detector can only return the corners
//! in *some* labelling together with the target's symmetry, the set of labellings it
//! cannot tell apart ([`TargetSymmetry`]: each element a permutation of the corner ids
//! and the target-frame transform that goes with it).
//!
//! **Within one robot** the motion decides. For views `i`, `j` the relative camera motion
//! `A_ij = camera_i_from_target * inverse(camera_j_from_target)` and the relative flange
//! motion `B_ij = inverse(base_from_flange_i) * base_from_flange_j` satisfy
//! `A_ij = X⁻¹ B_ij X` whatever the hand-eye `X` is, so both have the same rotation angle
//! and the same translation along the screw axis. Relabelling view `j` by element `S`
//! replaces `camera_j_from_target` by `camera_j_from_target * S⁻¹` and so changes `A_ij`
//! (typically by far: a turn by 180° about the board normal turns a 30° relative motion
//! into one of 150° or more), while the true labelling keeps the invariants within the
//! pose noise. [`resolve_labelling`] scores every pair of views under every relative
//! element, builds a first labelling along the most decisive pairs (a maximum spanning
//! tree from the most decisive view), improves it view by view against all pairs, fixes
//! view 0's labelling (so the result is "the detector's labelling of view 0") and
//! reports for each view how much worse its best alternative labelling fits. A view whose
//! alternatives fit about as well is *undecided*: the classic case is a pair of views
//! related by a 90° turn about the board normal, where the half-turned labelling is the
//! same motion turned the other way (see the tests).
//!
//! **Between two robots** motion cannot decide: relabelling all of robot 2's views by `S`
//! turns `base1_from_base2` by `S` about the board normal and every residual stays the
//! same. Only something physical can: [`resolve_between_robots`] uses gravity, i.e. that
//! both bases stand upright (their z axes are the same vertical), which decides the turn
//! when the board is tilted enough out of the horizontal.

use nalgebra::{Point3, Vector3};

use crate::{CalibError, Iso3};

/// Two transforms closer than this (m, rad) are taken as the same symmetry element.
const SAME_ELEMENT_TOL: f64 = 1e-6;

/// One labelling a target cannot tell apart from the reference one.
#[derive(Debug, Clone, PartialEq)]
pub struct SymmetryElement {
    /// What the element is, for messages ("identity", "turn by 180° about the board normal").
    pub name: String,
    /// `permutation[m]` is the id that corner `m` gets in the relabelled frame.
    pub permutation: Vec<usize>,
    /// `S`: maps the target point of corner `m` to that of `permutation[m]`:
    /// `point[permutation[m]] = S * point[m]`. Relabelling a view by this element
    /// replaces `camera_from_target` by `camera_from_target * S⁻¹`.
    pub target_transform: Iso3,
}

/// The labellings of a target that look the same (a group, the identity first).
#[derive(Debug, Clone, PartialEq)]
pub struct TargetSymmetry {
    elements: Vec<SymmetryElement>,
    /// `mul[a][b]`: the element with transform `S_a * S_b`.
    mul: Vec<Vec<usize>>,
    inv: Vec<usize>,
}

impl TargetSymmetry {
    /// No symmetry: only the identity, over `corners` corners.
    pub fn trivial(corners: usize) -> TargetSymmetry {
        TargetSymmetry {
            elements: vec![SymmetryElement {
                name: "identity".into(),
                permutation: (0..corners).collect(),
                target_transform: Iso3::identity(),
            }],
            mul: vec![vec![0]],
            inv: vec![0],
        }
    }

    /// Checks and indexes a symmetry group: the first element must be the identity,
    /// every permutation a permutation of `points`' ids agreeing with its transform
    /// (within 1e-9 m), and the set closed under composition and inverse.
    pub fn new(
        elements: Vec<SymmetryElement>,
        points: &[Point3<f64>],
    ) -> Result<TargetSymmetry, CalibError> {
        let bad = |element: usize, reason: String| CalibError::InvalidSymmetry { element, reason };
        if elements.is_empty() {
            return Err(bad(0, "no elements (the identity must come first)".into()));
        }
        if !same_transform(&elements[0].target_transform, &Iso3::identity()) {
            return Err(bad(0, "the first element is not the identity".into()));
        }
        for (e, el) in elements.iter().enumerate() {
            if el.permutation.len() != points.len() {
                return Err(bad(
                    e,
                    format!(
                        "permutation has {} entries for {} points",
                        el.permutation.len(),
                        points.len()
                    ),
                ));
            }
            let mut seen = vec![false; points.len()];
            for (m, &to) in el.permutation.iter().enumerate() {
                if to >= points.len() || std::mem::replace(&mut seen[to], true) {
                    return Err(bad(e, format!("not a permutation at corner {m} (-> {to})")));
                }
                let moved = el.target_transform * points[m];
                if (moved - points[to]).norm() > 1e-9 {
                    return Err(bad(
                        e,
                        format!(
                            "corner {m} moved by the transform lands {:.3e} m from corner {to}",
                            (moved - points[to]).norm()
                        ),
                    ));
                }
            }
        }
        let find = |t: &Iso3| {
            elements
                .iter()
                .position(|el| same_transform(&el.target_transform, t))
        };
        let n = elements.len();
        let mut mul = vec![vec![0; n]; n];
        let mut inv = vec![0; n];
        for a in 0..n {
            let ta = elements[a].target_transform;
            inv[a] = find(&ta.inverse())
                .ok_or_else(|| bad(a, "its inverse is not in the set".into()))?;
            for b in 0..n {
                mul[a][b] = find(&(ta * elements[b].target_transform)).ok_or_else(|| {
                    bad(a, format!("composed with element {b} it leaves the set"))
                })?;
            }
        }
        Ok(TargetSymmetry { elements, mul, inv })
    }

    /// The turns of a planar `cols x rows` grid of points `(i·square, j·square, 0)`
    /// (id `j·cols + i`) about its centre that map the grid onto itself: the identity
    /// and the half-turn, plus the two quarter turns when `quarter_turns` (only for
    /// `cols == rows`; ignored otherwise).
    pub fn grid_turns(
        cols: usize,
        rows: usize,
        square_m: f64,
        quarter_turns: bool,
    ) -> TargetSymmetry {
        let (w, h) = (
            (cols as f64 - 1.0) * square_m,
            (rows as f64 - 1.0) * square_m,
        );
        let id = |i: usize, j: usize| j * cols + i;
        let turn = |angle: f64, t: Vector3<f64>| {
            Iso3::from_parts(
                t.into(),
                nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle),
            )
        };
        let mut elements = vec![SymmetryElement {
            name: "identity".into(),
            permutation: (0..cols * rows).collect(),
            target_transform: Iso3::identity(),
        }];
        let square = quarter_turns && cols == rows;
        if square {
            // +90° about z: (x, y) -> (w - y, x), corner (i, j) -> (cols-1-j, i).
            elements.push(SymmetryElement {
                name: "turn by 90° about the board normal".into(),
                permutation: (0..cols * rows)
                    .map(|m| id(cols - 1 - m / cols, m % cols))
                    .collect(),
                target_transform: turn(std::f64::consts::FRAC_PI_2, Vector3::new(w, 0.0, 0.0)),
            });
        }
        elements.push(SymmetryElement {
            name: "turn by 180° about the board normal".into(),
            permutation: (0..cols * rows)
                .map(|m| id(cols - 1 - m % cols, rows - 1 - m / cols))
                .collect(),
            target_transform: turn(std::f64::consts::PI, Vector3::new(w, h, 0.0)),
        });
        if square {
            // -90° about z: (x, y) -> (y, h - x), corner (i, j) -> (j, rows-1-i).
            elements.push(SymmetryElement {
                name: "turn by 270° about the board normal".into(),
                permutation: (0..cols * rows)
                    .map(|m| id(m / cols, rows - 1 - m % cols))
                    .collect(),
                target_transform: turn(-std::f64::consts::FRAC_PI_2, Vector3::new(0.0, h, 0.0)),
            });
        }
        let points: Vec<Point3<f64>> = (0..cols * rows)
            .map(|m| {
                Point3::new(
                    (m % cols) as f64 * square_m,
                    (m / cols) as f64 * square_m,
                    0.0,
                )
            })
            .collect();
        // The elements above are a group by construction; `new` only indexes them.
        match TargetSymmetry::new(elements, &points) {
            Ok(s) => s,
            Err(_) => TargetSymmetry::trivial(cols * rows),
        }
    }

    /// The elements, the identity first.
    pub fn elements(&self) -> &[SymmetryElement] {
        &self.elements
    }

    /// Number of labellings that look the same (1: no symmetry).
    pub fn len(&self) -> usize {
        self.elements.len()
    }

    /// Always false: the identity is always there.
    pub fn is_empty(&self) -> bool {
        self.elements.is_empty()
    }

    /// Whether only the identity is in the group (the target fixes its own labelling).
    pub fn is_trivial(&self) -> bool {
        self.elements.len() == 1
    }

    /// The element with transform `S_a * S_b`.
    pub fn compose(&self, a: usize, b: usize) -> usize {
        self.mul[a][b]
    }

    /// The element with transform `S_a⁻¹`.
    pub fn inverse(&self, a: usize) -> usize {
        self.inv[a]
    }

    /// `camera_from_target` of a view relabelled by element `k`: `camera_from_target * S_k⁻¹`.
    pub fn relabel_pose(&self, camera_from_target: &Iso3, k: usize) -> Iso3 {
        camera_from_target * self.elements[k].target_transform.inverse()
    }

    /// The target points of a view's corners relabelled by element `k` (`S_k * p`);
    /// the pixels stay where they are, in the same order.
    pub fn relabel_points(&self, points: &[Point3<f64>], k: usize) -> Vec<Point3<f64>> {
        let s = self.elements[k].target_transform;
        points.iter().map(|p| s * p).collect()
    }

    /// One view's labelling from a prior on where the target is: the element
    /// whose relabelled pose turns the target nearest to `expected` (the camera's
    /// view of the target that, e.g., a setup sheet's approximate board pose and
    /// the mount's drawing give). Decided only when the nearest is within
    /// `max_angle_rad` of the prior and every other element is at least
    /// `max_angle_rad` farther from it: a prior off by more than the elements
    /// are apart cannot choose.
    ///
    /// This is how an agent that publishes each capture as it is taken labels a
    /// symmetric board; offline, [`resolve_labelling`] decides from the motion
    /// without a prior.
    pub fn label_by_prior(
        &self,
        camera_from_target: &Iso3,
        expected: &Iso3,
        max_angle_rad: f64,
    ) -> PriorLabelling {
        let mut angles: Vec<(f64, usize)> = (0..self.len())
            .map(|k| {
                let r = self.relabel_pose(camera_from_target, k).rotation;
                (r.angle_to(&expected.rotation), k)
            })
            .collect();
        angles.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (best_rad, k) = angles[0];
        let runner_up_rad = angles.get(1).map_or(f64::INFINITY, |a| a.0);
        let decided = best_rad <= max_angle_rad && runner_up_rad - best_rad >= max_angle_rad;
        PriorLabelling {
            element: decided.then_some(k),
            best_rad,
            runner_up_rad,
        }
    }
}

/// What [`TargetSymmetry::label_by_prior`] found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PriorLabelling {
    /// The labelling, when the prior decides it.
    pub element: Option<usize>,
    /// The nearest labelling's angle from the prior, and the next one's (rad).
    pub best_rad: f64,
    pub runner_up_rad: f64,
}

fn same_transform(a: &Iso3, b: &Iso3) -> bool {
    (a.translation.vector - b.translation.vector).norm() < SAME_ELEMENT_TOL
        && a.rotation.angle_to(&b.rotation) < SAME_ELEMENT_TOL
}

/// How pairs of views are scored by [`resolve_labelling`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LabellingOptions {
    /// Expected disagreement of the rotation angles of `A_ij` and `B_ij` (rad): camera
    /// pose noise plus robot error.
    pub sigma_angle_rad: f64,
    /// Expected disagreement of the translations along the screw axis (m).
    pub sigma_axial_m: f64,
    /// Below this rotation angle (rad) the screw axis is too poorly defined to compare
    /// translations along it; such pairs are scored on the angle alone.
    pub min_axis_angle_rad: f64,
    /// A pair's squared normalised disagreement is capped here, so one bad view cannot
    /// outvote the others (25: five sigmas).
    pub max_pair_cost: f64,
    /// A view is decided when its best alternative labelling costs at least this much
    /// more, summed over its pairs (16: one pair at four sigmas).
    pub min_margin: f64,
}

impl Default for LabellingOptions {
    fn default() -> Self {
        LabellingOptions {
            sigma_angle_rad: 0.5_f64.to_radians(),
            sigma_axial_m: 0.005,
            min_axis_angle_rad: 10_f64.to_radians(),
            max_pair_cost: 25.0,
            min_margin: 16.0,
        }
    }
}

/// One view's chosen labelling and how clearly the motion chose it.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewLabelling {
    /// The element to relabel the view by ([`TargetSymmetry::relabel_pose`]).
    pub element: usize,
    /// Summed pair cost of the chosen labelling (0 = the invariants agree exactly).
    pub cost: f64,
    /// How much more the best other labelling costs (infinite without alternatives).
    pub margin: f64,
    /// That best other labelling.
    pub runner_up: Option<usize>,
    /// Pairs with this view in which the runner-up costs at least a quarter of
    /// `min_margin` more than the chosen labelling.
    pub decisive_pairs: usize,
    /// Whether `margin >= min_margin`.
    pub decided: bool,
}

/// The per-view labellings chosen by [`resolve_labelling`], view 0 fixed.
#[derive(Debug, Clone, PartialEq)]
pub struct LabellingResolution {
    pub views: Vec<ViewLabelling>,
}

impl LabellingResolution {
    /// Indices of the views the motion could not decide.
    pub fn undecided(&self) -> Vec<usize> {
        (0..self.views.len())
            .filter(|&v| !self.views[v].decided)
            .collect()
    }
}

/// Rotation angle in [0, π] and |translation along the screw axis| of a rigid motion,
/// both unchanged by conjugation (`X⁻¹ M X` has the same).
fn screw_invariants(m: &Iso3) -> (f64, Option<f64>) {
    let angle = m.rotation.angle();
    let axial = m
        .rotation
        .axis()
        .map(|axis| m.translation.vector.dot(&axis.into_inner()).abs());
    (angle, axial)
}

/// Chooses each view's labelling of a symmetric target so that its motion agrees with
/// the robot's (see the module docs). `base_from_flange[i]` and `camera_from_target[i]`
/// (in the detector's labelling) belong to view `i`. The result relabels view `i` by
/// `views[i].element`; view 0 keeps its labelling (element 0). When view 0 itself is
/// undecided (a bad pose), the others' labellings still agree among themselves.
pub fn resolve_labelling(
    base_from_flange: &[Iso3],
    camera_from_target: &[Iso3],
    symmetry: &TargetSymmetry,
    options: &LabellingOptions,
) -> Result<LabellingResolution, CalibError> {
    let n = base_from_flange.len();
    if camera_from_target.len() != n {
        return Err(CalibError::MismatchedLengths {
            len_a: n,
            what_a: "flange poses",
            len_b: camera_from_target.len(),
            what_b: "board poses",
        });
    }
    for (i, (b, c)) in base_from_flange.iter().zip(camera_from_target).enumerate() {
        let finite = |m: &Iso3| {
            m.translation.vector.iter().all(|v| v.is_finite())
                && m.rotation.coords.iter().all(|v| v.is_finite())
        };
        if !finite(b) || !finite(c) {
            return Err(CalibError::NonFinite(format!("the poses of view {i}")));
        }
    }
    let g = symmetry.len();
    if g == 1 || n <= 1 {
        return Ok(LabellingResolution {
            views: (0..n)
                .map(|_| ViewLabelling {
                    element: 0,
                    cost: 0.0,
                    margin: f64::INFINITY,
                    runner_up: None,
                    decisive_pairs: 0,
                    decided: true,
                })
                .collect(),
        });
    }
    // cost[(i * n + j) * g + h]: pair (i, j) with relative element h = k_i⁻¹ k_j, i.e.
    // A_ij = C_i S_h C_j⁻¹ (the relabellings C_i S_{k_i}⁻¹ and C_j S_{k_j}⁻¹ give
    // C_i S_{k_i}⁻¹ S_{k_j} C_j⁻¹).
    let mut cost = vec![0.0; n * n * g];
    for i in 0..n {
        for j in i + 1..n {
            let b = base_from_flange[i].inverse() * base_from_flange[j];
            let (b_angle, b_axial) = screw_invariants(&b);
            for h in 0..g {
                let s = symmetry.elements[h].target_transform;
                let a = camera_from_target[i] * s * camera_from_target[j].inverse();
                let (a_angle, a_axial) = screw_invariants(&a);
                let mut c = ((a_angle - b_angle) / options.sigma_angle_rad).powi(2);
                if a_angle.min(b_angle) >= options.min_axis_angle_rad
                    && let (Some(da), Some(db)) = (a_axial, b_axial)
                {
                    c += ((da - db) / options.sigma_axial_m).powi(2);
                }
                let c = if c.is_finite() {
                    c.min(options.max_pair_cost)
                } else {
                    options.max_pair_cost
                };
                cost[(i * n + j) * g + h] = c;
                // A_ji = A_ij⁻¹ has the same invariants; its relative element is h⁻¹.
                cost[(j * n + i) * g + symmetry.inv[h]] = c;
            }
        }
    }
    let pair = |i: usize, j: usize, h: usize| cost[(i * n + j) * g + h];
    // Best element and margin of each pair on its own.
    let pair_best = |i: usize, j: usize| {
        let mut order: Vec<usize> = (0..g).collect();
        order.sort_by(|&a, &b| pair(i, j, a).total_cmp(&pair(i, j, b)));
        (order[0], pair(i, j, order[1]) - pair(i, j, order[0]))
    };
    // Maximum spanning tree by pair margin, from the view with the most decisive pairs.
    let root = (0..n)
        .max_by(|&a, &b| {
            let sum = |v: usize| {
                (0..n)
                    .filter(|&u| u != v)
                    .map(|u| pair_best(v, u).1)
                    .sum::<f64>()
            };
            sum(a).total_cmp(&sum(b))
        })
        .unwrap_or(0);
    let mut label: Vec<Option<usize>> = vec![None; n];
    label[root] = Some(0);
    for _ in 1..n {
        let mut best: Option<(usize, usize, f64)> = None;
        for i in 0..n {
            let Some(ki) = label[i] else { continue };
            for (j, lj) in label.iter().enumerate() {
                if lj.is_some() {
                    continue;
                }
                let (h, margin) = pair_best(i, j);
                if best.is_none_or(|(_, _, m)| margin > m) {
                    best = Some((j, symmetry.mul[ki][h], margin));
                }
            }
        }
        if let Some((j, k, _)) = best {
            label[j] = Some(k);
        }
    }
    let mut label: Vec<usize> = label.into_iter().map(|k| k.unwrap_or(0)).collect();
    // The cost of view j under element k, the others fixed.
    let view_cost = |label: &[usize], j: usize, k: usize| {
        (0..n)
            .filter(|&i| i != j)
            .map(|i| pair(i, j, symmetry.mul[symmetry.inv[label[i]]][k]))
            .sum::<f64>()
    };
    // Improve view by view (each step lowers the total cost, so this ends).
    for _ in 0..20 {
        let mut changed = false;
        for j in 0..n {
            let best = (0..g)
                .min_by(|&a, &b| view_cost(&label, j, a).total_cmp(&view_cost(&label, j, b)))
                .unwrap_or(label[j]);
            if view_cost(&label, j, best) < view_cost(&label, j, label[j]) - 1e-9 {
                label[j] = best;
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    // Fix view 0's labelling: left-multiply by k_0⁻¹ (relative elements are unchanged).
    let to_view0 = symmetry.inv[label[0]];
    for k in &mut label {
        *k = symmetry.mul[to_view0][*k];
    }
    let views = (0..n)
        .map(|j| {
            let chosen = view_cost(&label, j, label[j]);
            let runner_up = (0..g)
                .filter(|&k| k != label[j])
                .min_by(|&a, &b| view_cost(&label, j, a).total_cmp(&view_cost(&label, j, b)));
            let margin = runner_up.map_or(f64::INFINITY, |k| view_cost(&label, j, k) - chosen);
            let decisive_pairs = runner_up.map_or(0, |r| {
                (0..n)
                    .filter(|&i| i != j)
                    .filter(|&i| {
                        let rel = |k: usize| pair(i, j, symmetry.mul[symmetry.inv[label[i]]][k]);
                        rel(r) - rel(label[j]) >= 0.25 * options.min_margin
                    })
                    .count()
            });
            ViewLabelling {
                element: label[j],
                cost: chosen,
                margin,
                runner_up,
                decisive_pairs,
                decided: margin >= options.min_margin,
            }
        })
        .collect();
    Ok(LabellingResolution { views })
}

/// How gravity decides the turn between two robots' labellings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityOptions {
    /// The chosen turn must bring the two robots' "up" (each base's z axis, seen in
    /// the target frame) within this angle (rad): floor and cart tilt plus estimate error.
    pub max_up_disagreement_rad: f64,
    /// Every other turn must disagree by at least this much more (rad).
    pub min_up_separation_rad: f64,
}

impl Default for GravityOptions {
    fn default() -> Self {
        GravityOptions {
            max_up_disagreement_rad: 5_f64.to_radians(),
            min_up_separation_rad: 10_f64.to_radians(),
        }
    }
}

/// What gravity says about the labelling between two robots.
#[derive(Debug, Clone, PartialEq)]
pub struct BetweenRobots {
    /// The element to relabel all of robot 2's views by, if gravity decides.
    pub element: Option<usize>,
    /// Per element: angle (rad) between robot 1's up and robot 2's up relabelled by it.
    pub up_angles: Vec<f64>,
    /// The board plane's tilt out of the horizontal seen from robot 1 (rad, 0 = lying flat
    /// or upside down, π/2 = vertical).
    pub board_tilt_rad: f64,
}

/// Decides which element relabels robot 2's views so that both robots see the same
/// labelling, assuming both bases stand upright (base z = up for both). The board's
/// turn about its normal changes the in-plane part of "up" seen in the target frame,
/// so the turn is decided when the board is tilted out of the horizontal (a half-turn
/// moves "up" by twice the tilt); a horizontal board leaves it undecided.
/// `base_from_target` of each robot is in its own labelling (after [`resolve_labelling`]).
pub fn resolve_between_robots(
    base1_from_target: &Iso3,
    base2_from_target: &Iso3,
    symmetry: &TargetSymmetry,
    options: &GravityOptions,
) -> BetweenRobots {
    let up1 = base1_from_target.rotation.inverse() * Vector3::z();
    let up2 = base2_from_target.rotation.inverse() * Vector3::z();
    // Relabelling robot 2 by S gives base2_from_target * S⁻¹: up in the new frame is S·up2.
    let up_angles: Vec<f64> = symmetry
        .elements
        .iter()
        .map(|el| (el.target_transform.rotation * up2).angle(&up1))
        .collect();
    let board_tilt_rad = up1.z.abs().clamp(0.0, 1.0).acos();
    let mut order: Vec<usize> = (0..up_angles.len()).collect();
    order.sort_by(|&a, &b| up_angles[a].total_cmp(&up_angles[b]));
    let best = order[0];
    let separated = order
        .get(1)
        .is_none_or(|&r| up_angles[r] - up_angles[best] >= options.min_up_separation_rad);
    let element = (up_angles[best] <= options.max_up_disagreement_rad && separated).then_some(best);
    BetweenRobots {
        element,
        up_angles,
        board_tilt_rad,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{SynthConfig, random_robot};
    use nalgebra::{Translation3, UnitQuaternion};
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn cfg(cols: usize, rows: usize, captures: usize, pixel_sigma: f64) -> SynthConfig {
        SynthConfig {
            captures,
            board_cols: cols,
            board_rows: rows,
            pixel_sigma,
            ..SynthConfig::default()
        }
    }

    /// Scrambles each view's labelling by a random element; returns the scrambled
    /// poses and the element each view was relabelled by.
    fn scramble(poses: &[Iso3], sym: &TargetSymmetry, seed: u64) -> (Vec<Iso3>, Vec<usize>) {
        let mut rng = StdRng::seed_from_u64(seed);
        let ks: Vec<usize> = poses
            .iter()
            .map(|_| rng.random_range(0..sym.len()))
            .collect();
        let scrambled = poses
            .iter()
            .zip(&ks)
            .map(|(c, &k)| sym.relabel_pose(c, k))
            .collect();
        (scrambled, ks)
    }

    /// The chosen element undoes the scramble up to one global element.
    fn check_undone(sym: &TargetSymmetry, res: &LabellingResolution, ks: &[usize]) {
        // Relabelling by k then by e gives C S_k⁻¹ S_e⁻¹ = C (S_e S_k)⁻¹.
        let total: Vec<usize> = res
            .views
            .iter()
            .zip(ks)
            .map(|(v, &k)| sym.compose(v.element, k))
            .collect();
        assert!(
            total.iter().all(|&t| t == total[0]),
            "per-view total relabelling {total:?} (scramble {ks:?}) is not one global element"
        );
        assert_eq!(res.views[0].element, 0, "view 0 keeps its labelling");
    }

    #[test]
    fn grid_turns_are_groups_that_map_the_grid_onto_itself() {
        for (cols, rows, quarter, len) in [(8, 6, false, 2), (6, 6, true, 4), (5, 5, false, 2)] {
            let sym = TargetSymmetry::grid_turns(cols, rows, 0.03, quarter);
            assert_eq!(sym.len(), len, "{cols}x{rows}");
            let pts = crate::synth::board_points(cols, rows, 0.03);
            // `new` re-checks the permutations against the transforms.
            TargetSymmetry::new(sym.elements().to_vec(), &pts).unwrap();
            for k in 0..len {
                assert_eq!(sym.compose(k, sym.inverse(k)), 0);
            }
        }
        // A half-turn that does not match its permutation is refused.
        let pts = crate::synth::board_points(8, 6, 0.03);
        let mut els = TargetSymmetry::grid_turns(8, 6, 0.03, false)
            .elements()
            .to_vec();
        els[1].target_transform = Iso3::identity();
        let err = TargetSymmetry::new(els, &pts).unwrap_err();
        assert!(
            matches!(err, CalibError::InvalidSymmetry { element: 1, .. }),
            "{err}"
        );
    }

    #[test]
    fn motion_recovers_scrambled_half_turns_with_noise() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.025, false);
        for (seed, sigma) in [(1, 0.2), (2, 0.5), (3, 1.0)] {
            let robot = random_robot(seed, &cfg(8, 6, 12, sigma)).unwrap();
            let (scrambled, ks) = scramble(&robot.camera_from_target, &sym, seed + 100);
            let res = resolve_labelling(
                &robot.base_from_flange,
                &scrambled,
                &sym,
                &LabellingOptions::default(),
            )
            .unwrap();
            let margins: Vec<String> = res
                .views
                .iter()
                .map(|v| format!("{:.0}", v.margin))
                .collect();
            let costs: Vec<String> = res.views.iter().map(|v| format!("{:.2}", v.cost)).collect();
            eprintln!(
                "seed {seed}, pixel sigma {sigma}: margins {margins:?}, chosen costs {costs:?}"
            );
            check_undone(&sym, &res, &ks);
            assert!(res.undecided().is_empty(), "{:?}", res.undecided());
            for v in &res.views {
                assert!(v.margin >= 100.0, "margin {}", v.margin);
                // 11 pairs per view, each well below the 25 cap under the true labelling.
                assert!(v.cost < 11.0 * 5.0, "cost {}", v.cost);
            }
        }
    }

    #[test]
    fn motion_recovers_scrambled_quarter_turns_of_a_square_board() {
        let sym = TargetSymmetry::grid_turns(6, 6, 0.03, true);
        let robot = random_robot(7, &cfg(6, 6, 10, 0.3)).unwrap();
        let (scrambled, ks) = scramble(&robot.camera_from_target, &sym, 8);
        let res = resolve_labelling(
            &robot.base_from_flange,
            &scrambled,
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap();
        eprintln!(
            "6x6, 4 turns: scramble {ks:?}, chosen {:?}, least margin {:.0}",
            res.views.iter().map(|v| v.element).collect::<Vec<_>>(),
            res.views
                .iter()
                .map(|v| v.margin)
                .fold(f64::INFINITY, f64::min)
        );
        check_undone(&sym, &res, &ks);
        assert!(res.undecided().is_empty());
    }

    #[test]
    fn a_bad_view_is_left_undecided_and_the_others_still_agree() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.025, false);
        let robot = random_robot(4, &cfg(8, 6, 10, 0.3)).unwrap();
        let (mut scrambled, ks) = scramble(&robot.camera_from_target, &sym, 5);
        // View 0 (the anchor) gets a board pose 20° and 5 cm off: no labelling fits it.
        scrambled[0] = Iso3::from_parts(
            Translation3::new(0.05, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 20_f64.to_radians()),
        ) * scrambled[0];
        let res = resolve_labelling(
            &robot.base_from_flange,
            &scrambled,
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap();
        eprintln!(
            "bad view 0: margins {:?}",
            res.views
                .iter()
                .map(|v| format!("{:.0}", v.margin))
                .collect::<Vec<_>>()
        );
        assert_eq!(res.undecided(), vec![0]);
        let total: Vec<usize> = (1..ks.len())
            .map(|v| sym.compose(res.views[v].element, ks[v]))
            .collect();
        assert!(total.iter().all(|&t| t == total[0]), "{total:?}");
    }

    /// Two views related by a 90° turn of the camera about the board normal through the
    /// board centre: the half-turned labelling makes the camera motion a −90° turn about
    /// the same line, with the same angle and no axial translation, exactly as the robot's
    /// own motion. No pair can decide.
    #[test]
    fn a_quarter_turn_about_the_board_normal_cannot_decide() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.025, false);
        let centre = Point3::new(3.5 * 0.025, 2.5 * 0.025, 0.0);
        let camera0_from_target = Iso3::from_parts(
            Translation3::new(0.01, -0.02, 0.5),
            UnitQuaternion::identity(),
        ) * Iso3::translation(-centre.x, -centre.y, 0.0);
        // Turn the target (equivalently the camera) by 90° about the board normal at its centre.
        let turn = Iso3::translation(centre.x, centre.y, 0.0)
            * Iso3::rotation(Vector3::z() * std::f64::consts::FRAC_PI_2)
            * Iso3::translation(-centre.x, -centre.y, 0.0);
        let camera1_from_target = camera0_from_target * turn;
        let flange_from_camera = Iso3::from_parts(
            Translation3::new(0.03, -0.05, 0.06),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 1.3),
        );
        let base_from_target = Iso3::from_parts(
            Translation3::new(0.6, 0.1, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let flange = |c: &Iso3| base_from_target * c.inverse() * flange_from_camera.inverse();
        let base_from_flange = [flange(&camera0_from_target), flange(&camera1_from_target)];
        let res = resolve_labelling(
            &base_from_flange,
            &[camera0_from_target, camera1_from_target],
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap();
        eprintln!(
            "quarter turn about the normal: margins {:?}",
            res.views.iter().map(|v| v.margin).collect::<Vec<_>>()
        );
        assert_eq!(res.undecided(), vec![0, 1]);
        assert!(res.views.iter().all(|v| v.margin.abs() < 1e-6));
        // A third view off the normal decides all of them.
        let tilt = Iso3::translation(centre.x, centre.y, 0.0)
            * Iso3::rotation(Vector3::new(0.4, 0.2, 0.3))
            * Iso3::translation(-centre.x, -centre.y, 0.0);
        let camera2_from_target = camera0_from_target * tilt;
        let res = resolve_labelling(
            &[
                base_from_flange[0],
                base_from_flange[1],
                flange(&camera2_from_target),
            ],
            &[
                camera0_from_target,
                camera1_from_target,
                camera2_from_target,
            ],
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap();
        assert!(res.undecided().is_empty(), "{res:?}");
        assert!(res.views.iter().all(|v| v.element == 0), "{res:?}");
    }

    #[test]
    fn inputs_of_different_lengths_or_not_finite_are_refused() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.025, false);
        let err = resolve_labelling(
            &[Iso3::identity(); 3],
            &[Iso3::identity(); 2],
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, CalibError::MismatchedLengths { .. }), "{err}");
        let nan = Iso3::translation(f64::NAN, 0.0, 0.0);
        let err = resolve_labelling(
            &[Iso3::identity(), nan],
            &[Iso3::identity(); 2],
            &sym,
            &LabellingOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, CalibError::NonFinite(_)), "{err}");
    }

    #[test]
    fn gravity_decides_a_tilted_board_and_not_a_flat_one() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.025, false);
        let base1_from_base2 = Iso3::from_parts(
            Translation3::new(1.0, 0.05, 0.01),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 3.0),
        );
        for (tilt_deg, decided) in [(0.0, false), (3.0, false), (20.0, true), (60.0, true)] {
            let base1_from_target = Iso3::from_parts(
                Translation3::new(0.5, 0.0, 0.1),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3)
                    * UnitQuaternion::from_axis_angle(
                        &Vector3::x_axis(),
                        std::f64::consts::PI - f64::to_radians(tilt_deg),
                    ),
            );
            // Robot 2 sees the board half-turned, and its base is 0.5° off upright.
            let base2_from_target = Iso3::rotation(Vector3::x() * 0.5_f64.to_radians())
                * base1_from_base2.inverse()
                * base1_from_target
                * sym.elements()[1].target_transform.inverse();
            let r = resolve_between_robots(
                &base1_from_target,
                &base2_from_target,
                &sym,
                &GravityOptions::default(),
            );
            eprintln!(
                "board tilt {tilt_deg}°: measured {:.1}°, up angles {:?} deg, element {:?}",
                r.board_tilt_rad.to_degrees(),
                r.up_angles
                    .iter()
                    .map(|a| format!("{:.1}", a.to_degrees()))
                    .collect::<Vec<_>>(),
                r.element
            );
            assert!((r.board_tilt_rad.to_degrees() - tilt_deg).abs() < 0.01);
            // Relabelling robot 2 by the half-turn undoes what was done to it.
            assert_eq!(r.element, decided.then_some(1), "tilt {tilt_deg}");
        }
    }

    #[test]
    fn a_prior_within_its_bound_chooses_the_labelling_and_a_wrong_one_cannot() {
        let sym = TargetSymmetry::grid_turns(8, 6, 0.03, false);
        // The true view of the board, and the detector's answer in the other labelling.
        let truth = Iso3::from_parts(
            Vector3::new(0.02, -0.01, 0.5).into(),
            nalgebra::UnitQuaternion::from_euler_angles(3.0, 0.2, 0.4),
        );
        let detected = truth * sym.elements()[1].target_transform;
        let bound = 45f64.to_radians();
        for (prior_off_deg, decided) in [
            (0.0, true),
            (10.0, true),
            (40.0, true),
            (60.0, false),
            (90.0, false),
        ] {
            let off = nalgebra::UnitQuaternion::from_scaled_axis(
                Vector3::new(0.3, 1.0, 0.4).normalize() * f64::to_radians(prior_off_deg),
            );
            let expected = Iso3::from_parts(truth.translation, truth.rotation * off);
            let l = sym.label_by_prior(&detected, &expected, bound);
            if decided {
                let k = l
                    .element
                    .unwrap_or_else(|| panic!("{prior_off_deg}° undecided: {l:?}"));
                let relabelled = sym.relabel_pose(&detected, k);
                assert!(relabelled.rotation.angle_to(&truth.rotation) < 1e-9);
                assert!((relabelled.translation.vector - truth.translation.vector).norm() < 1e-9);
            } else {
                assert_eq!(l.element, None, "{prior_off_deg}°: {l:?}");
            }
        }
        // A target without symmetry: the prior has nothing to choose, whatever it says.
        let plain = TargetSymmetry::trivial(48);
        let far = Iso3::from_parts(
            truth.translation,
            truth.rotation * nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 3.0),
        );
        assert_eq!(plain.label_by_prior(&truth, &truth, bound).element, Some(0));
        assert_eq!(plain.label_by_prior(&truth, &far, bound).element, None);
    }
}
