//! Dataset locations and copies shared by the pipeline's tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// A dataset nobody here made, read from `../shared/datasets` beside the checkout.
pub fn shared_dataset(name: &str) -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/datasets")
        .join(name);
    assert!(
        p.is_dir(),
        "shared dataset missing: {} (the tests read it from beside the checkout)",
        p.display()
    );
    p
}

/// A dataset committed in `datasets/`.
pub fn bundled(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../datasets")
        .join(name)
}

/// Copies a folder tree (a dataset to change in a temporary folder).
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

pub mod opencv_peer;
pub mod split;
