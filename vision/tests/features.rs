//! Feature detection and matching: a textured image against a known shift of itself,
//! the ratio test and cross-check, every feature kind, and degenerate input.

use std::path::{Path, PathBuf};

use b2b_vision::GrayImage;
use b2b_vision::features::{
    FeatureKind, FeatureOptions, Features, detect_features, load_depth, match_features,
    match_features_among, match_images,
};

/// A deterministic blocky texture (like the simulator's boxes), `w x h`.
fn texture(w: u32, h: u32, seed: u64) -> Vec<u8> {
    let mut s = seed;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let cell = 6u32;
    let (cw, ch) = (w / cell + 2, h / cell + 2);
    let blocks: Vec<u8> = (0..cw * ch).map(|_| (next() % 256) as u8).collect();
    let mut px = vec![0u8; (w * h) as usize];
    for v in 0..h {
        for u in 0..w {
            // Two scales of blocks so that there are corners at several sizes.
            let a = blocks[((v / cell) * cw + u / cell) as usize];
            let b = blocks[((v / (3 * cell)) * cw + u / (3 * cell) + 1) as usize];
            px[(v * w + u) as usize] = ((a as u32 + b as u32) / 2) as u8;
        }
    }
    px
}

/// `img` shifted by (dx, dy) integer pixels: pixel (u, v) of the result is (u - dx, v - dy).
fn shifted(px: &[u8], w: u32, h: u32, dx: i64, dy: i64) -> Vec<u8> {
    let mut out = vec![0u8; px.len()];
    for v in 0..h as i64 {
        for u in 0..w as i64 {
            let (su, sv) = (u - dx, v - dy);
            if su >= 0 && sv >= 0 && su < w as i64 && sv < h as i64 {
                out[(v * w as i64 + u) as usize] = px[(sv * w as i64 + su) as usize];
            }
        }
    }
    out
}

fn dataset_image(robot: &str, k: usize) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets/sim-rgbd-boxes-2x5")
        .join(robot)
        .join(format!("images/{k:03}.png"))
}

/// Every kind finds matches on a shifted texture, and they agree with the shift:
/// 90 % of the matches within 1 px of it (4 px for ORB).
#[test]
fn every_kind_matches_a_known_shift() {
    let (w, h) = (424, 240);
    let base = texture(w, h, 12345);
    let (dx, dy) = (17, -9);
    let a = GrayImage::from_raw(w, h, &base).unwrap();
    let b = GrayImage::from_raw(w, h, &shifted(&base, w, h, dx, dy)).unwrap();
    for kind in [FeatureKind::Sift, FeatureKind::Akaze, FeatureKind::Orb] {
        let opts = FeatureOptions {
            kind,
            ..Default::default()
        };
        let m = match_images(&a, &b, &opts).unwrap();
        // ORB's keypoints on coarse pyramid levels are placed on that level's grid
        // (up to 1.2^7 px), so its positions are only good to a few pixels.
        let tol = if kind == FeatureKind::Orb { 4.0 } else { 1.0 };
        let good = m
            .iter()
            .filter(|m| {
                let d = m.pixel2 - m.pixel1;
                (d.x - dx as f64).abs() < tol && (d.y - dy as f64).abs() < tol
            })
            .count();
        eprintln!("{}: {} matches, {good} on the shift", kind.name(), m.len());
        assert!(m.len() >= 30, "{}: {} matches", kind.name(), m.len());
        assert!(
            good as f64 >= 0.9 * m.len() as f64,
            "{}: {good}/{} on the shift",
            kind.name(),
            m.len()
        );
        for x in &m {
            assert!(x.ratio < 0.75);
        }
    }
}

/// Cross-check keeps only mutual best matches: every index appears at most once on
/// each side, and turning it off can only add matches.
#[test]
fn cross_check_gives_one_to_one_matches() {
    let a = b2b_vision::load_gray(&dataset_image("robot1", 0)).unwrap();
    let b = b2b_vision::load_gray(&dataset_image("robot2", 0)).unwrap();
    let opts = FeatureOptions::default();
    let fa = detect_features(&a, &opts).unwrap();
    let fb = detect_features(&b, &opts).unwrap();
    assert!(
        fa.len() > 100 && fb.len() > 100,
        "{} {}",
        fa.len(),
        fb.len()
    );
    let m = match_features(&fa, &fb, &opts).unwrap();
    let mut i1: Vec<_> = m.iter().map(|m| m.index1).collect();
    let mut i2: Vec<_> = m.iter().map(|m| m.index2).collect();
    i1.sort_unstable();
    i1.dedup();
    i2.sort_unstable();
    i2.dedup();
    assert_eq!(i1.len(), m.len());
    assert_eq!(i2.len(), m.len());
    let loose = match_features(
        &fa,
        &fb,
        &FeatureOptions {
            cross_check: false,
            ..opts
        },
    )
    .unwrap();
    assert!(loose.len() >= m.len());
    // A stricter ratio keeps fewer.
    let strict = match_features(&fa, &fb, &FeatureOptions { ratio: 0.5, ..opts }).unwrap();
    assert!(strict.len() < m.len(), "{} vs {}", strict.len(), m.len());
}

/// A flat image has no features and gives no matches (not an error); bad options
/// and mixed kinds are errors that say why.
#[test]
fn degenerate_input() {
    let flat = GrayImage::from_raw(200, 100, &[128u8; 200 * 100]).unwrap();
    let tex = GrayImage::from_raw(424, 240, &texture(424, 240, 9)).unwrap();
    let opts = FeatureOptions::default();
    let f = detect_features(&flat, &opts).unwrap();
    assert!(f.is_empty());
    let t = detect_features(&tex, &opts).unwrap();
    assert!(match_features(&f, &t, &opts).unwrap().is_empty());
    let bad = FeatureOptions { ratio: 1.5, ..opts };
    assert!(
        match_features(&t, &t, &bad)
            .unwrap_err()
            .to_string()
            .contains("ratio")
    );
    let orb = detect_features(
        &tex,
        &FeatureOptions {
            kind: FeatureKind::Orb,
            ..opts
        },
    )
    .unwrap();
    let err = match_features(&t, &orb, &opts).unwrap_err().to_string();
    assert!(err.contains("sift") && err.contains("orb"), "{err}");
    assert!(
        FeatureKind::parse("surf")
            .unwrap_err()
            .to_string()
            .contains("SURF")
    );
    assert_eq!(FeatureKind::parse("AKAZE").unwrap(), FeatureKind::Akaze);
}

/// Matching among listed candidates, with every pair listed, is OpenCV's
/// brute-force matching: the same matches for every kind (up to the odd
/// ratio at the edge of the test, where float sums may differ in the last bit).
#[test]
fn matching_among_every_pair_is_brute_force_matching() {
    let a = b2b_vision::load_gray(&dataset_image("robot1", 0)).unwrap();
    let b = b2b_vision::load_gray(&dataset_image("robot2", 0)).unwrap();
    for kind in [FeatureKind::Sift, FeatureKind::Akaze, FeatureKind::Orb] {
        let opts = FeatureOptions {
            kind,
            ..Default::default()
        };
        let fa = detect_features(&a, &opts).unwrap();
        let fb = detect_features(&b, &opts).unwrap();
        let everything: Vec<Vec<usize>> = vec![(0..fb.len()).collect(); fa.len()];
        let ours = match_features_among(&fa, &fb, &everything, &opts).unwrap();
        let opencv = match_features(&fa, &fb, &opts).unwrap();
        let key = |m: &b2b_vision::features::FeatureMatch| (m.index1, m.index2);
        let ours_keys: std::collections::BTreeSet<_> = ours.iter().map(key).collect();
        let cv_keys: std::collections::BTreeSet<_> = opencv.iter().map(key).collect();
        let differ = ours_keys.symmetric_difference(&cv_keys).count();
        eprintln!(
            "{}: {} matches among every pair, {} brute force, {differ} differ",
            kind.name(),
            ours.len(),
            opencv.len()
        );
        assert!(opencv.len() >= 20, "{}: {}", kind.name(), opencv.len());
        assert!(
            differ * 100 <= opencv.len(),
            "{}: {differ} differ",
            kind.name()
        );
        for m in &ours {
            let cv = opencv.iter().find(|c| key(c) == key(m));
            if let Some(cv) = cv {
                assert!(
                    (m.distance - cv.distance).abs() <= 1e-3 * cv.distance.max(1.0),
                    "{}: distance {} against OpenCV's {}",
                    kind.name(),
                    m.distance,
                    cv.distance
                );
            }
        }
    }
}

/// A pattern repeated across the image defeats the ratio test (every feature
/// has a twin as good as itself); candidates from where the features should
/// be seen again tell the twins apart. Bad candidate lists are errors.
#[test]
fn candidates_tell_a_repeated_pattern_apart() {
    let (tw, h) = (212u32, 240u32);
    let tile = texture(tw, h, 777);
    let w = 2 * tw;
    let mut base = vec![0u8; (w * h) as usize];
    for v in 0..h {
        for u in 0..w {
            base[(v * w + u) as usize] = tile[(v * tw + u % tw) as usize];
        }
    }
    let (dx, dy) = (5i64, 3i64);
    let a = GrayImage::from_raw(w, h, &base).unwrap();
    let b = GrayImage::from_raw(w, h, &shifted(&base, w, h, dx, dy)).unwrap();
    let opts = FeatureOptions::default();
    let fa = detect_features(&a, &opts).unwrap();
    let fb = detect_features(&b, &opts).unwrap();
    let brute = match_features(&fa, &fb, &opts).unwrap();
    // Candidates: b's features within 8 px of where a's should be.
    let near: Vec<Vec<usize>> = fa
        .pixels
        .iter()
        .map(|p| {
            let q = nalgebra::Point2::new(p.x + dx as f64, p.y + dy as f64);
            (0..fb.len())
                .filter(|j| (fb.pixels[*j] - q).norm() < 8.0)
                .collect()
        })
        .collect();
    let guided = match_features_among(&fa, &fb, &near, &opts).unwrap();
    let on_shift = |m: &&b2b_vision::features::FeatureMatch| {
        let d = m.pixel2 - m.pixel1;
        (d.x - dx as f64).abs() < 1.0 && (d.y - dy as f64).abs() < 1.0
    };
    let good = guided.iter().filter(on_shift).count();
    eprintln!(
        "repeated pattern: {} features; brute force {} matches, among candidates {} ({good} on the shift)",
        fa.len(),
        brute.len(),
        guided.len()
    );
    assert!(
        guided.len() >= 3 * brute.len().max(10),
        "{} vs {}",
        guided.len(),
        brute.len()
    );
    assert!(good * 10 >= guided.len() * 9, "{good}/{}", guided.len());
    let err = match_features_among(&fa, &fb, &near[1..], &opts)
        .unwrap_err()
        .to_string();
    assert!(err.contains("candidate lists"), "{err}");
    let mut beyond = near.clone();
    beyond[3] = vec![fb.len()];
    let err = match_features_among(&fa, &fb, &beyond, &opts)
        .unwrap_err()
        .to_string();
    assert!(err.contains("feature 3's candidate"), "{err}");
}

#[test]
fn depth_images_load_and_refuse_8_bit() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5/robot1");
    let d = load_depth(&dir.join("depth/000.png")).unwrap();
    assert_eq!((d.width, d.height), (424, 240));
    let valid: Vec<u16> = d.data.iter().copied().filter(|v| *v > 0).collect();
    assert!(valid.len() > d.data.len() / 2);
    // Half a metre or so, in millimetres.
    let mean = valid.iter().map(|v| f64::from(*v)).sum::<f64>() / valid.len() as f64;
    assert!((200.0..1500.0).contains(&mean), "{mean}");
    let err = load_depth(&dir.join("images/000.png"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("16-bit"), "{err}");
    let err = load_depth(&dir.join("depth/missing.png"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing.png"), "{err}");
}

/// `max_features` keeps the strongest features of every kind, and the kept
/// descriptors still belong to the kept keypoints (matching a truncated set against
/// itself pairs every feature with itself).
#[test]
fn max_features_truncates_consistently() {
    let img = GrayImage::from_raw(424, 240, &texture(424, 240, 77)).unwrap();
    for kind in [FeatureKind::Sift, FeatureKind::Akaze, FeatureKind::Orb] {
        let opts = FeatureOptions {
            kind,
            max_features: 50,
            ..Default::default()
        };
        let f = detect_features(&img, &opts).unwrap();
        // ORB limits itself, spread over its pyramid, and may return fewer.
        if kind == FeatureKind::Orb {
            assert!((20..=50).contains(&f.len()), "orb: {}", f.len());
        } else {
            assert_eq!(f.len(), 50, "{}", kind.name());
        }
        let all = detect_features(
            &img,
            &FeatureOptions {
                max_features: 0,
                ..opts
            },
        )
        .unwrap();
        assert!(all.len() > 50, "{}: {}", kind.name(), all.len());
        let mut strongest = all.responses.clone();
        strongest.sort_by(|a, b| b.total_cmp(a));
        let weakest_kept = f.responses.iter().copied().fold(f64::INFINITY, f64::min);
        if kind != FeatureKind::Orb {
            assert!(weakest_kept >= strongest[50], "{}", kind.name());
        }
        let m = match_features(&f, &f, &FeatureOptions { ratio: 1.0, ..opts }).unwrap();
        let selfmatched = m.iter().filter(|m| m.index1 == m.index2).count();
        assert!(
            selfmatched * 10 >= f.len() * 9,
            "{}: {selfmatched}/{}",
            kind.name(),
            f.len()
        );
    }
}

/// Features cross a process boundary as bytes: for every kind, the rebuilt features
/// match exactly as the originals (SIFT's float descriptors are whole numbers
/// 0..=255, so one byte each holds them); inconsistent parts are refused with the
/// counts.
#[test]
fn features_round_trip_through_bytes() {
    let a = b2b_vision::load_gray(&dataset_image("robot1", 0)).unwrap();
    let b = b2b_vision::load_gray(&dataset_image("robot2", 0)).unwrap();
    for kind in [FeatureKind::Sift, FeatureKind::Akaze, FeatureKind::Orb] {
        let opts = FeatureOptions {
            kind,
            ..FeatureOptions::default()
        };
        let fa = detect_features(&a, &opts).unwrap();
        let fb = detect_features(&b, &opts).unwrap();
        let (len, bytes) = fa.descriptor_bytes().unwrap();
        assert_eq!(bytes.len(), len * fa.len());
        let back = Features::from_parts(kind, fa.pixels.clone(), fa.responses.clone(), len, &bytes)
            .unwrap();
        assert_eq!(back.descriptor_bytes().unwrap(), (len, bytes.clone()));
        let direct = match_features(&fa, &fb, &opts).unwrap();
        let rebuilt = match_features(&back, &fb, &opts).unwrap();
        assert_eq!(direct, rebuilt, "{}", kind.name());
        assert!(!direct.is_empty());
        // Wrong sizes name the counts.
        let err = Features::from_parts(
            kind,
            fa.pixels.clone(),
            fa.responses.clone(),
            len,
            &bytes[1..],
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("bytes"), "{err}");
        let err = Features::from_parts(kind, fa.pixels.clone(), vec![], len, &bytes)
            .unwrap_err()
            .to_string();
        assert!(err.contains("responses"), "{err}");
    }
    let err = Features::from_parts(
        FeatureKind::Sift,
        vec![nalgebra::Point2::new(1.0, 2.0)],
        vec![0.1],
        64,
        &[0u8; 64],
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("128"), "{err}");
}
