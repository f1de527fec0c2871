//! The pinhole camera with OpenCV's distortion model, and its Jacobians.
//!
//! The model is OpenCV's (`k1, k2, p1, p2, k3[, k4, k5, k6]`), so intrinsics
//! estimated by OpenCV or written in a dataset's `dataset.json` mean the same thing
//! here. Jacobians are analytic because the joint refinement evaluates them for
//! every board corner in every iteration; a test checks them against finite
//! differences.

use nalgebra::{Matrix2x3, Point2, Point3, SMatrix, Vector2};

use crate::CalibError;

/// Number of intrinsic parameters the refinement can estimate:
/// `fx, fy, cx, cy, k1, k2, p1, p2, k3`.
pub const N_INTRINSICS: usize = 9;

/// A pinhole camera with OpenCV distortion. Pixels are OpenCV's: the centre of the
/// top-left pixel is (0, 0).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraModel {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `k1, k2, p1, p2, k3, k4, k5, k6`; missing trailing terms are zero.
    pub dist: [f64; 8],
}

impl CameraModel {
    /// Builds a camera from OpenCV-ordered coefficients (4, 5 or 8 of them; more
    /// terms, thin prism and tilt, are not supported and rejected).
    pub fn new(
        width: u32,
        height: u32,
        [fx, fy, cx, cy]: [f64; 4],
        dist: &[f64],
    ) -> Result<Self, CalibError> {
        if dist.len() > 8 {
            return Err(CalibError::DistortionTerms { count: dist.len() });
        }
        if [fx, fy, cx, cy].iter().chain(dist).any(|v| !v.is_finite()) {
            return Err(CalibError::NonFinite("camera intrinsics".into()));
        }
        if fx <= 0.0 || fy <= 0.0 {
            return Err(CalibError::NonPositiveFocalLength { fx, fy });
        }
        let mut d = [0.0; 8];
        d[..dist.len()].copy_from_slice(dist);
        Ok(CameraModel {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            dist: d,
        })
    }

    /// The intrinsic parameter vector `fx, fy, cx, cy, k1, k2, p1, p2, k3`.
    pub fn params(&self) -> [f64; N_INTRINSICS] {
        let d = &self.dist;
        [
            self.fx, self.fy, self.cx, self.cy, d[0], d[1], d[2], d[3], d[4],
        ]
    }

    /// Sets the parameters returned by [`CameraModel::params`].
    pub fn set_params(&mut self, p: &[f64; N_INTRINSICS]) {
        self.fx = p[0];
        self.fy = p[1];
        self.cx = p[2];
        self.cy = p[3];
        self.dist[..5].copy_from_slice(&p[4..9]);
    }

    /// Distorts normalised image coordinates, returning also the 2x2 Jacobian
    /// `d(xd, yd) / d(x, y)`.
    fn distort(&self, x: f64, y: f64) -> (f64, f64, [[f64; 2]; 2], f64) {
        distort_normalised(&self.dist, x, y)
    }

    /// Projects a point in the camera frame. `None` when it is not in front of
    /// the camera.
    pub fn project(&self, p_in_camera: &Point3<f64>) -> Option<Point2<f64>> {
        if p_in_camera.z <= 1e-9 {
            return None;
        }
        let x = p_in_camera.x / p_in_camera.z;
        let y = p_in_camera.y / p_in_camera.z;
        let (xd, yd, _, _) = self.distort(x, y);
        Some(Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// Projects a point and returns `d(u, v) / d(p_in_camera)`.
    pub fn project_with_jacobian(&self, p: &Point3<f64>) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        if p.z <= 1e-9 {
            return None;
        }
        let iz = 1.0 / p.z;
        let x = p.x * iz;
        let y = p.y * iz;
        let (xd, yd, j, _) = self.distort(x, y);
        // d(x, y)/d(P) = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        let dxy = Matrix2x3::new(iz, 0.0, -x * iz, 0.0, iz, -y * iz);
        let jd = nalgebra::Matrix2::new(
            self.fx * j[0][0],
            self.fx * j[0][1],
            self.fy * j[1][0],
            self.fy * j[1][1],
        );
        Some((
            Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy),
            jd * dxy,
        ))
    }

    /// `d(u, v) / d(fx, fy, cx, cy, k1, k2, p1, p2, k3)` at a point in the camera
    /// frame (for the rational model's k4..k6 held fixed).
    pub fn intrinsics_jacobian(&self, p: &Point3<f64>) -> Option<SMatrix<f64, 2, N_INTRINSICS>> {
        if p.z <= 1e-9 {
            return None;
        }
        let x = p.x / p.z;
        let y = p.y / p.z;
        let (xd, yd, _, r2) = self.distort(x, y);
        let [_, _, _, _, _, k4, k5, k6] = self.dist;
        let den = 1.0 + k4 * r2 + k5 * r2 * r2 + k6 * r2 * r2 * r2;
        let (fx, fy) = (self.fx, self.fy);
        let r4 = r2 * r2;
        let r6 = r4 * r2;
        let mut j = SMatrix::<f64, 2, N_INTRINSICS>::zeros();
        j[(0, 0)] = xd;
        j[(1, 1)] = yd;
        j[(0, 2)] = 1.0;
        j[(1, 3)] = 1.0;
        j[(0, 4)] = fx * x * r2 / den;
        j[(1, 4)] = fy * y * r2 / den;
        j[(0, 5)] = fx * x * r4 / den;
        j[(1, 5)] = fy * y * r4 / den;
        j[(0, 6)] = fx * 2.0 * x * y;
        j[(1, 6)] = fy * (r2 + 2.0 * y * y);
        j[(0, 7)] = fx * (r2 + 2.0 * x * x);
        j[(1, 7)] = fy * 2.0 * x * y;
        j[(0, 8)] = fx * x * r6 / den;
        j[(1, 8)] = fy * y * r6 / den;
        Some(j)
    }

    /// Whether a pixel lies inside the image.
    pub fn contains(&self, uv: &Point2<f64>) -> bool {
        uv.x >= -0.5
            && uv.y >= -0.5
            && uv.x <= self.width as f64 - 0.5
            && uv.y <= self.height as f64 - 0.5
    }

    /// Removes distortion from a pixel by fixed-point iteration (OpenCV's
    /// `undistortPoints` approach), returning normalised coordinates.
    pub fn unproject(&self, uv: &Point2<f64>) -> Vector2<f64> {
        let xd = (uv.x - self.cx) / self.fx;
        let yd = (uv.y - self.cy) / self.fy;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..30 {
            let (ex, ey, _, _) = self.distort(x, y);
            x -= ex - xd;
            y -= ey - yd;
        }
        Vector2::new(x, y)
    }
}

/// OpenCV's distortion of normalised image coordinates `(x, y)` with coefficients
/// `k1, k2, p1, p2, k3, k4, k5, k6`: the distorted coordinates, the 2x2 Jacobian
/// `d(xd, yd) / d(x, y)` and `r²`. Shared by the camera model and the simulator's
/// renderer, so the two can never disagree.
pub fn distort_normalised(dist: &[f64; 8], x: f64, y: f64) -> (f64, f64, [[f64; 2]; 2], f64) {
    let [k1, k2, p1, p2, k3, k4, k5, k6] = *dist;

    let r2 = x * x + y * y;
    let r4 = r2 * r2;
    let r6 = r4 * r2;
    let num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6;
    let den = 1.0 + k4 * r2 + k5 * r4 + k6 * r6;
    let radial = num / den;
    let dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4;
    let dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4;
    let drad = (dnum * den - num * dden) / (den * den);
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let j = [
        [
            radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x,
            2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y,
        ],
        [
            2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y,
            radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x,
        ],
    ];
    (xd, yd, j, r2)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> CameraModel {
        CameraModel::new(
            1280,
            720,
            [910.0, 905.0, 640.0, 360.0],
            &[0.08, -0.15, 0.001, -0.002, 0.05],
        )
        .unwrap()
    }

    #[test]
    fn point_jacobian_matches_finite_differences() {
        let cam = camera();
        let p = Point3::new(0.12, -0.08, 0.6);
        let (_, j) = cam.project_with_jacobian(&p).unwrap();
        for k in 0..3 {
            let h = 1e-6;
            let mut a = p;
            let mut b = p;
            a[k] += h;
            b[k] -= h;
            let d = (cam.project(&a).unwrap() - cam.project(&b).unwrap()) / (2.0 * h);
            assert!(
                (d[0] - j[(0, k)]).abs() < 1e-4 && (d[1] - j[(1, k)]).abs() < 1e-4,
                "{k}: {d} vs {j}"
            );
        }
    }

    #[test]
    fn intrinsics_jacobian_matches_finite_differences() {
        let cam = camera();
        let p = Point3::new(-0.2, 0.1, 0.7);
        let j = cam.intrinsics_jacobian(&p).unwrap();
        for k in 0..N_INTRINSICS {
            let h = 1e-7;
            let (mut a, mut b) = (cam.clone(), cam.clone());
            let mut pa = cam.params();
            let mut pb = cam.params();
            pa[k] += h;
            pb[k] -= h;
            a.set_params(&pa);
            b.set_params(&pb);
            let d = (a.project(&p).unwrap() - b.project(&p).unwrap()) / (2.0 * h);
            assert!(
                (d[0] - j[(0, k)]).abs() < 1e-3 && (d[1] - j[(1, k)]).abs() < 1e-3,
                "{k}: {d} vs {j}"
            );
        }
    }

    #[test]
    fn unproject_inverts_project() {
        let cam = camera();
        let p = Point3::new(0.2, -0.15, 0.9);
        let uv = cam.project(&p).unwrap();
        let n = cam.unproject(&uv);
        assert!((n - Vector2::new(p.x / p.z, p.y / p.z)).norm() < 1e-10);
    }

    #[test]
    fn points_behind_the_camera_do_not_project() {
        assert!(camera().project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn too_many_coefficients_are_rejected() {
        assert!(CameraModel::new(10, 10, [1.0, 1.0, 5.0, 5.0], &[0.0; 12]).is_err());
    }
}
