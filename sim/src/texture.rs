//! What is printed on a surface: reflectance as a function of position.
//!
//! A [`Texture`] answers, for a point `(x, y)` in metres in its surface's frame, the
//! diffuse reflectance there (0 = black, 1 = a perfect white) **and the id of a convex
//! region of constant reflectance** holding the point. The region ids are what makes the
//! renderer both exact and fast: when the four corners of a pixel's footprint land in
//! the same convex region of the same convex surface, the whole footprint is inside it
//! (a convex set contains the convex hull of its points), so the pixel is uniform and
//! one sample is exact. Only pixels that straddle a boundary are supersampled. Textures
//! that vary continuously answer [`VARYING`] and are always supersampled.
//!
//! Procedural textures are exact (a checkerboard's edges are where the geometry says,
//! with no bitmap resampling). Marker boards come in as [`BitmapTexture`]s: a bitmap
//! made elsewhere (e.g. an ArUco marker image from the vision crate), each bitmap cell a
//! square region.

use std::fmt::Debug;

/// The region id of a texture that varies continuously at a point.
pub const VARYING: u32 = u32::MAX;

/// Reflectance of white printer paper (matte, diffuse).
pub const PAPER_WHITE: f32 = 0.85;
/// Reflectance of black laser-printer toner.
pub const TONER_BLACK: f32 = 0.04;

/// One lookup: reflectance and the convex region of constant reflectance it lies in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TexSample {
    pub reflectance: f32,
    pub region: u32,
}

/// Reflectance on a surface, in the surface's own metric coordinates.
pub trait Texture: Debug + Send + Sync {
    /// The reflectance at `(x, y)` metres, and its region (see the module docs).
    fn sample(&self, x: f64, y: f64) -> TexSample;

    /// The colour of the print at `(x, y)`: per-channel (red, green, blue) factors on
    /// the reflectance with luminance `0.299 r + 0.587 g + 0.114 b = 1`, so that the
    /// grey rendering is the same. Constant over each region of [`Texture::sample`]
    /// (or the texture answers [`VARYING`]). Paper, toner and grey: `[1, 1, 1]`.
    fn tint(&self, _x: f64, _y: f64) -> [f32; 3] {
        [1.0; 3]
    }
}

/// A tint of hue `hue` (radians) and saturation `saturation` (0..1) with luminance 1.
pub fn tint_from_hue(hue: f32, saturation: f32) -> [f32; 3] {
    use std::f32::consts::TAU;
    let c = [0.0, TAU / 3.0, 2.0 * TAU / 3.0].map(|o| 1.0 + saturation * (hue - o).cos());
    let luminance = 0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2];
    c.map(|v| v / luminance)
}

/// The same reflectance everywhere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Uniform(pub f32);

impl Texture for Uniform {
    fn sample(&self, _x: f64, _y: f64) -> TexSample {
        TexSample {
            reflectance: self.0,
            region: 0,
        }
    }
}

/// A printed checkerboard in the target frame of shared/dataset-format.md: inner corner
/// `(i, j)` at `(i·square, j·square)`, the origin touching a black outer-corner square.
/// Square `(a, b)` (`a` in `-1..=cols-1`, `b` in `-1..=rows-1`) covers
/// `[a·s, (a+1)·s] × [b·s, (b+1)·s]` and is black when `a + b` is even. Outside the
/// squares is white paper (the border); the board's [`Checkerboard::extent`] adds
/// `margin` on every side.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Checkerboard {
    /// Inner corners along x (columns) and y (rows).
    pub inner_corners: [u32; 2],
    pub square_m: f64,
    /// White border around the squares, m.
    pub margin_m: f64,
    pub white: f32,
    pub black: f32,
}

impl Checkerboard {
    /// A board of paper and toner.
    pub fn new(inner_corners: [u32; 2], square_m: f64, margin_m: f64) -> Self {
        Checkerboard {
            inner_corners,
            square_m,
            margin_m,
            white: PAPER_WHITE,
            black: TONER_BLACK,
        }
    }

    /// The squares' bounding box `(min, max)` in the target frame.
    pub fn squares_extent(&self) -> ([f64; 2], [f64; 2]) {
        let s = self.square_m;
        let [c, r] = self.inner_corners;
        ([-s, -s], [c as f64 * s, r as f64 * s])
    }

    /// The printed sheet `(min, max)`: squares plus margin.
    pub fn extent(&self) -> ([f64; 2], [f64; 2]) {
        let (lo, hi) = self.squares_extent();
        let m = self.margin_m;
        ([lo[0] - m, lo[1] - m], [hi[0] + m, hi[1] + m])
    }

    /// Whether square `(a, b)` is black.
    pub fn is_black(a: i64, b: i64) -> bool {
        (a + b).rem_euclid(2) == 0
    }
}

impl Texture for Checkerboard {
    fn sample(&self, x: f64, y: f64) -> TexSample {
        let s = self.square_m;
        let (lo, hi) = self.squares_extent();
        // The border is split into four convex strips, so that every region is convex.
        let border = |region| TexSample {
            reflectance: self.white,
            region,
        };
        if x < lo[0] {
            return border(1);
        }
        if x >= hi[0] {
            return border(2);
        }
        if y < lo[1] {
            return border(3);
        }
        if y >= hi[1] {
            return border(4);
        }
        let a = (x / s).floor() as i64;
        let b = (y / s).floor() as i64;
        let cols = self.inner_corners[0] as i64 + 1;
        TexSample {
            reflectance: if Self::is_black(a, b) {
                self.black
            } else {
                self.white
            },
            region: 16 + ((b + 1) * cols + (a + 1)) as u32,
        }
    }
}

/// A bitmap printed with square cells of `cell_m`, its top-left corner at `origin_m`;
/// bitmap row `j` runs along +y. Points outside take the nearest edge cell, so the
/// surface carrying it should cover exactly the bitmap. Each cell is one region.
#[derive(Debug, Clone, PartialEq)]
pub struct BitmapTexture {
    pub width: usize,
    pub height: usize,
    /// Row-major grey levels, 0 = `black`, 255 = `white`.
    pub pixels: Vec<u8>,
    pub origin_m: [f64; 2],
    pub cell_m: f64,
    pub white: f32,
    pub black: f32,
}

impl BitmapTexture {
    /// Wraps a bitmap; `None` when the sizes do not agree or a size is zero.
    pub fn new(
        width: usize,
        height: usize,
        pixels: Vec<u8>,
        origin_m: [f64; 2],
        cell_m: f64,
    ) -> Option<Self> {
        (width > 0 && height > 0 && pixels.len() == width * height && cell_m > 0.0).then_some(
            BitmapTexture {
                width,
                height,
                pixels,
                origin_m,
                cell_m,
                white: PAPER_WHITE,
                black: TONER_BLACK,
            },
        )
    }
}

impl Texture for BitmapTexture {
    fn sample(&self, x: f64, y: f64) -> TexSample {
        let i = ((x - self.origin_m[0]) / self.cell_m).floor();
        let j = ((y - self.origin_m[1]) / self.cell_m).floor();
        let i = i.clamp(0.0, (self.width - 1) as f64) as usize;
        let j = j.clamp(0.0, (self.height - 1) as f64) as usize;
        let level = self.pixels[j * self.width + i] as f32 / 255.0;
        TexSample {
            reflectance: self.black + (self.white - self.black) * level,
            region: (j * self.width + i) as u32,
        }
    }
}

/// Random multi-scale "value noise" (a lattice of random grey levels, bilinearly
/// interpolated, over several octaves) with sharp-edged random blots on top: rich in
/// corners and blobs at every scale, which is what SIFT/AKAZE matching on the RGB-D
/// scene needs. Deterministic for its seed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseTexture {
    pub seed: u64,
    /// The coarsest lattice spacing, m; each further octave halves it.
    pub scale_m: f64,
    pub octaves: u32,
    /// Mean and spread of the reflectance.
    pub mean: f32,
    pub contrast: f32,
}

fn hash(seed: u64, i: i64, j: i64, octave: u32) -> f32 {
    // SplitMix64 finaliser over the lattice coordinates.
    let mut z = seed
        ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (octave as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 40) as f32 / (1u64 << 24) as f32
}

impl Texture for NoiseTexture {
    fn sample(&self, x: f64, y: f64) -> TexSample {
        let mut value = 0.0f32;
        let mut amplitude = 0.5f32;
        let mut total = 0.0f32;
        let mut scale = self.scale_m;
        for o in 0..self.octaves {
            let (u, v) = (x / scale, y / scale);
            let (i, j) = (u.floor(), v.floor());
            let (fu, fv) = ((u - i) as f32, (v - j) as f32);
            let (i, j) = (i as i64, j as i64);
            let h = |di, dj| hash(self.seed, i + di, j + dj, o);
            let top = h(0, 0) * (1.0 - fu) + h(1, 0) * fu;
            let bottom = h(0, 1) * (1.0 - fu) + h(1, 1) * fu;
            value += amplitude * (top * (1.0 - fv) + bottom * fv);
            total += amplitude;
            amplitude *= 0.6;
            scale *= 0.5;
        }
        let mut v = value / total - 0.5;
        // Sharp blots: the second octave's lattice cells, a third of them inked.
        let s = self.scale_m * 0.5;
        let (bi, bj) = ((x / s).floor() as i64, (y / s).floor() as i64);
        if hash(self.seed ^ 0xB10B, bi, bj, 99) < 0.33 {
            v = -0.5 + 0.2 * v;
        }
        TexSample {
            reflectance: (self.mean + 2.0 * self.contrast * v).clamp(0.02, 0.95),
            region: VARYING,
        }
    }

    /// Printed colour: a random hue per cell of the coarsest lattice, and a second,
    /// finer one on the blots, so colour edges add to the grey structure.
    fn tint(&self, x: f64, y: f64) -> [f32; 3] {
        let s = self.scale_m;
        let (i, j) = ((x / s).floor() as i64, (y / s).floor() as i64);
        let mut hue = hash(self.seed ^ 0xC010, i, j, 7) * std::f32::consts::TAU;
        let (bi, bj) = (
            (x / (0.5 * s)).floor() as i64,
            (y / (0.5 * s)).floor() as i64,
        );
        if hash(self.seed ^ 0xB10B, bi, bj, 99) < 0.33 {
            hue += std::f32::consts::PI;
        }
        tint_from_hue(hue, 0.45)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkerboard_colours_follow_the_format() {
        let b = Checkerboard::new([9, 6], 0.025, 0.01);
        let s = 0.025;
        // The outer-corner square touching the origin is black.
        assert_eq!(b.sample(-0.5 * s, -0.5 * s).reflectance, TONER_BLACK);
        // Its neighbours are white, and the first inner square is black again.
        assert_eq!(b.sample(0.5 * s, -0.5 * s).reflectance, PAPER_WHITE);
        assert_eq!(b.sample(-0.5 * s, 0.5 * s).reflectance, PAPER_WHITE);
        assert_eq!(b.sample(0.5 * s, 0.5 * s).reflectance, TONER_BLACK);
        // 10 x 7 squares: the opposite corner (8, 5) is white, so a 180° turn is visible.
        assert_eq!(b.sample(8.5 * s, 5.5 * s).reflectance, PAPER_WHITE);
        // Border.
        assert_eq!(b.sample(-1.2 * s, 0.0).reflectance, PAPER_WHITE);
    }

    #[test]
    fn bitmap_cells_are_regions() {
        let t = BitmapTexture::new(2, 2, vec![0, 255, 255, 0], [0.0, 0.0], 0.01).unwrap();
        assert_eq!(t.sample(0.005, 0.005).reflectance, TONER_BLACK);
        assert_eq!(t.sample(0.015, 0.005).reflectance, PAPER_WHITE);
        assert_eq!(t.sample(0.015, 0.015).region, 3);
        assert!(BitmapTexture::new(2, 2, vec![0; 3], [0.0, 0.0], 0.01).is_none());
    }

    #[test]
    fn noise_is_deterministic_and_in_range() {
        let t = NoiseTexture {
            seed: 7,
            scale_m: 0.04,
            octaves: 4,
            mean: 0.5,
            contrast: 0.4,
        };
        for k in 0..1000 {
            let (x, y) = (k as f64 * 0.0013, k as f64 * -0.0007);
            let a = t.sample(x, y);
            assert_eq!(a, t.sample(x, y));
            assert!((0.0..=1.0).contains(&a.reflectance));
        }
    }
}
