//! The sensors: irradiance to 8-bit pixels, true depth to a RealSense-like depth image.
//!
//! **Colour (grey) sensor.** The irradiance image is in digital numbers (DN). Photon
//! arrival is Poisson: a pixel collecting `N = DN · e_per_dn` electrons has shot noise
//! `√N` electrons, i.e. variance `DN / e_per_dn` in DN², so dim scenes are relatively
//! noisier, which is the point of the seed's 145 / 243 / 352 lx experiment. Read noise
//! adds a signal-independent Gaussian. For the ~10⁴ electrons of a bright pixel the
//! Gaussian approximation of Poisson is exact to far below one DN. The result is
//! quantised by rounding and clipped to 0..=255 (saturation).
//!
//! **Depth sensor.** An active stereo camera measures disparity with a sub-pixel error
//! `ε` (RealSense D4xx: ~0.08 px), so its depth RMS error is `z² · ε / (f · B)` — it
//! grows with the square of the distance (f: depth focal length in px, B: baseline).
//! Stereo matching fails where the surface jumps (the two imagers see different
//! things there; RealSense leaves such pixels 0), outside the working range, and at
//! random on poor texture (`dropout`). Values are written in `unit_m` steps
//! (1 mm for the D4xx's default depth unit), 0 meaning "no data".

use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::render::Irradiance;
use crate::{Rng, SimError};

/// An 8-bit grey image, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GreyImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

/// An 8-bit colour image, row-major, red-green-blue interleaved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

/// A 16-bit depth image, row-major, in sensor units; 0 = no data.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u16>,
    /// Metres per unit.
    pub unit_m: f64,
}

/// The grey sensor's noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorNoise {
    /// Electrons per DN (conversion gain). 0 disables shot noise.
    #[serde(default = "default_e_per_dn")]
    pub e_per_dn: f64,
    /// Read noise, DN (σ).
    #[serde(default = "default_read_noise")]
    pub read_noise_dn: f64,
}

fn default_e_per_dn() -> f64 {
    20.0
}

fn default_read_noise() -> f64 {
    1.0
}

impl Default for SensorNoise {
    /// A small CMOS sensor: ~5000 e⁻ full well over 255 DN, 1 DN read noise.
    fn default() -> Self {
        SensorNoise {
            e_per_dn: default_e_per_dn(),
            read_noise_dn: default_read_noise(),
        }
    }
}

impl SensorNoise {
    /// No noise: only rounding.
    pub fn none() -> Self {
        SensorNoise {
            e_per_dn: 0.0,
            read_noise_dn: 0.0,
        }
    }

    /// The standard deviation (DN) of a pixel whose mean is `dn`.
    pub fn sigma_dn(&self, dn: f64) -> f64 {
        let shot = if self.e_per_dn > 0.0 {
            dn.max(0.0) / self.e_per_dn
        } else {
            0.0
        };
        (shot + self.read_noise_dn * self.read_noise_dn).sqrt()
    }
}

/// Exposes the sensor: adds shot and read noise, rounds and saturates.
pub fn expose(irradiance: &Irradiance, noise: &SensorNoise, rng: &mut Rng) -> GreyImage {
    let noisy = noise.e_per_dn > 0.0 || noise.read_noise_dn > 0.0;
    let data = irradiance
        .dn
        .iter()
        .map(|&v| {
            let mut x = v as f64;
            if noisy {
                let z: f64 = StandardNormal.sample(rng);
                x += noise.sigma_dn(x) * z;
            }
            x.round().clamp(0.0, 255.0) as u8
        })
        .collect();
    GreyImage {
        width: irradiance.width,
        height: irradiance.height,
        data,
    }
}

/// Exposes a colour sensor: [`expose`] on each channel of [`Irradiance::rgb`] (the
/// grey irradiance on all three when the frame was rendered without colour).
pub fn expose_rgb(irradiance: &Irradiance, noise: &SensorNoise, rng: &mut Rng) -> RgbImage {
    let channels: Vec<f32> = if irradiance.rgb.is_empty() {
        irradiance.dn.iter().flat_map(|&v| [v; 3]).collect()
    } else {
        irradiance.rgb.iter().flatten().copied().collect()
    };
    let flat = Irradiance {
        width: channels.len(),
        height: 1,
        dn: channels,
        depth_m: vec![],
        rgb: vec![],
    };
    RgbImage {
        width: irradiance.width,
        height: irradiance.height,
        data: expose(&flat, noise, rng).data,
    }
}

/// The depth sensor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthModel {
    /// Disparity error, px (σ).
    #[serde(default = "d_subpixel")]
    pub subpixel: f64,
    /// Depth imagers' focal length, px.
    #[serde(default = "d_focal")]
    pub focal_px: f64,
    /// Stereo baseline, m.
    #[serde(default = "d_baseline")]
    pub baseline_m: f64,
    /// Working range, m.
    #[serde(default = "d_min")]
    pub min_m: f64,
    #[serde(default = "d_max")]
    pub max_m: f64,
    /// A pixel whose 4-neighbours differ in depth by more than this fraction is a hole.
    #[serde(default = "d_edge")]
    pub edge_jump: f64,
    /// Probability of a random hole.
    #[serde(default = "d_dropout")]
    pub dropout: f64,
    /// Metres per unit of the image.
    #[serde(default = "d_unit")]
    pub unit_m: f64,
}

fn d_subpixel() -> f64 {
    0.08
}
fn d_focal() -> f64 {
    640.0
}
fn d_baseline() -> f64 {
    0.05
}
fn d_min() -> f64 {
    0.105
}
fn d_max() -> f64 {
    6.0
}
fn d_edge() -> f64 {
    0.02
}
fn d_dropout() -> f64 {
    0.005
}
fn d_unit() -> f64 {
    0.001
}

impl Default for DepthModel {
    /// A RealSense D435 at 848x480: 50 mm baseline, 0.08 px sub-pixel error (2.5 mm RMS
    /// at 1 m), 1 mm units.
    fn default() -> Self {
        DepthModel {
            subpixel: d_subpixel(),
            focal_px: d_focal(),
            baseline_m: d_baseline(),
            min_m: d_min(),
            max_m: d_max(),
            edge_jump: d_edge(),
            dropout: d_dropout(),
            unit_m: d_unit(),
        }
    }
}

impl DepthModel {
    /// Depth RMS error at `z`, m.
    pub fn sigma_m(&self, z: f64) -> f64 {
        z * z * self.subpixel / (self.focal_px * self.baseline_m)
    }

    /// Checks the values.
    pub fn validate(&self) -> Result<(), SimError> {
        let ok = self.subpixel >= 0.0
            && self.focal_px > 0.0
            && self.baseline_m > 0.0
            && self.min_m >= 0.0
            && self.max_m > self.min_m
            && self.edge_jump > 0.0
            && (0.0..=1.0).contains(&self.dropout)
            && self.unit_m > 0.0;
        if ok {
            Ok(())
        } else {
            Err(SimError::invalid("depth model", format!("{self:?}")))
        }
    }

    /// The depth image of a rendered frame.
    pub fn measure(&self, irradiance: &Irradiance, rng: &mut Rng) -> DepthImage {
        let (w, h) = (irradiance.width, irradiance.height);
        let z = &irradiance.depth_m;
        let mut data = vec![0u16; w * h];
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                // Draw the noise for every pixel, so the random stream does not depend
                // on which pixels are holes.
                let noise: f64 = StandardNormal.sample(rng);
                let drop: f64 = rand::Rng::random(rng);
                let zi = z[i] as f64;
                if zi <= 0.0 || zi < self.min_m || zi > self.max_m || drop < self.dropout {
                    continue;
                }
                let neighbours = [
                    (u > 0).then(|| z[i - 1]),
                    (u + 1 < w).then(|| z[i + 1]),
                    (v > 0).then(|| z[i - w]),
                    (v + 1 < h).then(|| z[i + w]),
                ];
                let edge = neighbours
                    .iter()
                    .flatten()
                    .any(|&n| n <= 0.0 || (n as f64 - zi).abs() > self.edge_jump * zi);
                if edge {
                    continue;
                }
                let measured = zi + self.sigma_m(zi) * noise;
                data[i] = (measured / self.unit_m).round().clamp(1.0, 65535.0) as u16;
            }
        }
        DepthImage {
            width: w,
            height: h,
            data,
            unit_m: self.unit_m,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn flat(dn: f32, z: f32, w: usize, h: usize) -> Irradiance {
        Irradiance {
            width: w,
            height: h,
            dn: vec![dn; w * h],
            depth_m: vec![z; w * h],
            rgb: vec![],
        }
    }

    #[test]
    fn noise_has_the_shot_plus_read_variance() {
        let noise = SensorNoise::default();
        let mut rng = Rng::seed_from_u64(5);
        for level in [20.0f32, 100.0, 200.0] {
            let img = expose(&flat(level, 1.0, 200, 200), &noise, &mut rng);
            let n = img.data.len() as f64;
            let mean = img.data.iter().map(|&v| v as f64).sum::<f64>() / n;
            let var = img
                .data
                .iter()
                .map(|&v| (v as f64 - mean).powi(2))
                .sum::<f64>()
                / n;
            // Rounding adds 1/12 DN².
            let expected = noise.sigma_dn(level as f64).powi(2) + 1.0 / 12.0;
            assert!((mean - level as f64).abs() < 0.05, "{mean}");
            assert!(
                (var / expected - 1.0).abs() < 0.03,
                "{level}: {var} vs {expected}"
            );
        }
    }

    #[test]
    fn saturation_clips_at_255() {
        let img = expose(
            &flat(400.0, 1.0, 4, 4),
            &SensorNoise::none(),
            &mut Rng::seed_from_u64(1),
        );
        assert!(img.data.iter().all(|&v| v == 255));
    }

    #[test]
    fn depth_error_grows_with_distance_squared() {
        let model = DepthModel {
            dropout: 0.0,
            ..DepthModel::default()
        };
        let mut rng = Rng::seed_from_u64(6);
        for z in [0.5f32, 1.0, 2.0] {
            let d = model.measure(&flat(0.0, z, 200, 100), &mut rng);
            let m: Vec<f64> = d
                .data
                .iter()
                .map(|&v| v as f64 * d.unit_m - z as f64)
                .collect();
            let rms = (m.iter().map(|e| e * e).sum::<f64>() / m.len() as f64).sqrt();
            // Quantisation to 1 mm adds (1 mm)²/12.
            let expected = (model.sigma_m(z as f64).powi(2) + 1e-6 / 12.0).sqrt();
            assert!(
                (rms / expected - 1.0).abs() < 0.05,
                "{z}: {rms} vs {expected}"
            );
        }
    }

    #[test]
    fn depth_edges_and_missing_surfaces_are_holes() {
        let mut img = flat(0.0, 1.0, 10, 1);
        for z in &mut img.depth_m[5..] {
            *z = 2.0;
        }
        img.depth_m[0] = 0.0;
        let model = DepthModel {
            dropout: 0.0,
            subpixel: 0.0,
            ..DepthModel::default()
        };
        let d = model.measure(&img, &mut Rng::seed_from_u64(1));
        assert_eq!(d.data, vec![0, 0, 1000, 1000, 0, 0, 2000, 2000, 2000, 2000]);
    }
}
