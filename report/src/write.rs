//! Writing a result and its siblings all or nothing: a reader never sees a mix
//! of old and new files, nor half a file, and a destination a file cannot
//! replace (a directory, a pipe) or an output over its own input is refused
//! before any work.

use std::path::{Path, PathBuf};

use b2b_protocol::CalibrationResult;

use crate::ReportError;
use crate::formats::{opencv_yaml, ros_yaml, ros2_launch, sibling_paths, urdf};

/// Writes RESULT.json and its siblings ([`Siblings`](crate::formats::Siblings)) together
/// ([`write_together`]): all are replaced, or none.
pub fn write_result(path: &Path, r: &CalibrationResult) -> Result<(), ReportError> {
    let files = sibling_paths(path);
    let json = serde_json::to_string_pretty(r).map_err(|source| ReportError::Serialize {
        what: "result",
        source,
    })? + "\n";
    write_together(&[
        (path.to_owned(), json.into_bytes()),
        (files.ros_yaml, ros_yaml(r).into_bytes()),
        (files.opencv_yml, opencv_yaml(r)?.into_bytes()),
        (files.ros2_launch, ros2_launch(r).into_bytes()),
        (files.urdf, urdf(r)?.into_bytes()),
    ])
}

/// The temporary files of one [`write_together`] and the backups of the files
/// it replaces; whatever is still listed when it is dropped is removed.
#[derive(Debug, Default)]
struct Leftovers(Vec<PathBuf>);

impl Leftovers {
    fn keep(&mut self, path: &Path) {
        self.0.retain(|p| p != path);
    }
}

impl Drop for Leftovers {
    fn drop(&mut self) {
        for p in &self.0 {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// `.NAME.SUFFIX-PID` beside `path` (hidden, in the same folder so that a rename
/// replaces `path` in one step).
fn beside(path: &Path, suffix: &str) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{suffix}-{}", std::process::id()))
}

/// Writes the files of one result so that a reader never sees a mix of old and
/// new files, nor half a file: each file's bytes go to a temporary file in its
/// destination's folder (created when missing), flushed to disk; only when all
/// are written are they renamed over their destinations. A destination that is
/// a directory (or a pipe, a device) is refused before anything is written; a
/// failed write (a full disk) removes the temporary files and leaves every
/// previous file as it was; a rename failing half-way puts back the files
/// already replaced (kept as hard links until the end).
pub fn write_together(files: &[(PathBuf, Vec<u8>)]) -> Result<(), ReportError> {
    use std::io::Write;
    let paths: Vec<&Path> = files.iter().map(|(p, _)| p.as_path()).collect();
    check_destinations(&paths).map_err(|e| ReportError::NothingWritten {
        files: files.iter().map(|(p, _)| p.clone()).collect(),
        source: Box::new(e),
    })?;
    let mut leftovers = Leftovers::default();
    let mut temps = Vec::with_capacity(files.len());
    for (path, bytes) in files {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|source| ReportError::CreateFolder {
                path: parent.to_owned(),
                source,
            })?;
        }
        let tmp = beside(path, "tmp");
        let _ = std::fs::remove_file(&tmp);
        leftovers.0.push(tmp.clone());
        let written = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
            .and_then(|mut f| {
                f.write_all(bytes)?;
                f.sync_all()
            });
        written.map_err(|source| ReportError::WriteThrough {
            path: path.clone(),
            temporary: tmp.clone(),
            source,
        })?;
        temps.push(tmp);
    }
    // Keep each previous file under a second name until every rename is done.
    let mut backups: Vec<Option<PathBuf>> = Vec::with_capacity(files.len());
    for (path, _) in files {
        let backup = if path.is_file() {
            let b = beside(path, "previous");
            let _ = std::fs::remove_file(&b);
            leftovers.0.push(b.clone());
            std::fs::hard_link(path, &b)
                .or_else(|_| std::fs::copy(path, &b).map(|_| ()))
                .map_err(|source| ReportError::KeepPrevious {
                    path: path.clone(),
                    source,
                })?;
            Some(b)
        } else {
            None
        };
        backups.push(backup);
    }
    for (k, ((path, _), tmp)) in files.iter().zip(&temps).enumerate() {
        if let Err(e) = std::fs::rename(tmp, path) {
            // Put back what was replaced.
            for ((done, _), backup) in files.iter().zip(&backups).take(k) {
                match backup {
                    Some(b) => {
                        if std::fs::rename(b, done).is_ok() {
                            leftovers.keep(b);
                        }
                    }
                    None => {
                        let _ = std::fs::remove_file(done);
                    }
                }
            }
            return Err(ReportError::Replace {
                path: path.clone(),
                source: e,
            });
        }
        leftovers.keep(tmp);
    }
    Ok(())
}

/// Refuses destinations that could not be replaced by a file: a directory, a
/// named pipe, a device. Called by [`write_together`], and by the commands
/// before any work so that a long run does not end in a refusal.
pub fn check_destinations(paths: &[&Path]) -> Result<(), ReportError> {
    for path in paths {
        if let Ok(meta) = std::fs::metadata(path)
            && let Some(kind) = b2b_dataset::not_a_regular_file(&meta)
        {
            return Err(ReportError::NotReplaceable {
                path: path.to_path_buf(),
                kind,
            });
        }
    }
    Ok(())
}

/// `path` made absolute with every symlink resolved, component by component:
/// each existing prefix is canonicalised, so a later `..` steps out of the
/// real folder, and the part that does not exist (no symlinks there) is
/// applied as written.
fn resolved(path: &Path) -> PathBuf {
    use std::path::Component;
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_owned());
    let mut real = PathBuf::new();
    for part in abs.components() {
        match part {
            Component::Prefix(_) | Component::RootDir => real.push(part),
            Component::CurDir => {}
            Component::ParentDir => {
                real.pop();
            }
            Component::Normal(name) => {
                real.push(name);
                if let Ok(c) = real.canonicalize() {
                    real = c;
                }
            }
        }
    }
    real
}

/// Refuses an output `path` (given with `flag`) that is inside the input
/// dataset folder `dataset` or is one of the `inputs` files, after resolving
/// symlinks and `..`: a result is never written over what it was computed from.
/// Called before any work.
pub fn refuse_output_over_input(
    flag: &str,
    path: &Path,
    dataset: Option<&Path>,
    inputs: &[&Path],
) -> Result<(), ReportError> {
    let out = resolved(path);
    if let Some(dir) = dataset {
        let real = resolved(dir);
        if out.starts_with(&real) {
            return Err(ReportError::OutputInsideDataset {
                flag: flag.to_owned(),
                path: path.to_owned(),
                dataset: dir.to_owned(),
                resolved: out,
            });
        }
    }
    for input in inputs {
        if out == resolved(input) {
            return Err(ReportError::OutputIsInput {
                flag: flag.to_owned(),
                path: path.to_owned(),
                input: input.to_path_buf(),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The files of `dir`, by name, with their bytes (hidden ones included).
    fn listing(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                let bytes = if e.path().is_file() {
                    std::fs::read(e.path()).unwrap()
                } else {
                    vec![]
                };
                (e.file_name().to_string_lossy().into_owned(), bytes)
            })
            .collect();
        out.sort();
        out
    }

    /// A write that fails half-way (the third file's folder cannot be made: a
    /// file is in the way) replaces nothing and leaves no temporary file.
    #[test]
    fn a_failed_write_replaces_nothing_and_leaves_no_temporary_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        std::fs::write(dir.join("b.yaml"), "old b").unwrap();
        std::fs::write(dir.join("blocker"), "a file, not a folder").unwrap();
        let before = listing(dir);
        let e = write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("b.yaml"), b"new b".to_vec()),
            (dir.join("blocker/c.urdf"), b"new c".to_vec()),
        ])
        .unwrap_err();
        let text = b2b_errors::chain(&e);
        assert!(text.contains("blocker"), "{text}");
        assert_eq!(listing(dir), before);
    }

    /// A directory in the way of one file: refused before anything is written,
    /// naming it; the others are byte-identical.
    #[test]
    fn a_directory_in_the_way_replaces_nothing() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        std::fs::create_dir(dir.join("c.urdf")).unwrap();
        let before = listing(dir);
        let e = write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("c.urdf"), b"new c".to_vec()),
        ])
        .unwrap_err();
        let text = b2b_errors::chain(&e);
        assert!(
            text.contains("c.urdf is a directory") && text.contains("nothing was written"),
            "{text}"
        );
        assert_eq!(listing(dir), before);
    }

    /// The normal case: every file replaced, new ones created with their
    /// folder, no temporary or backup file left.
    #[test]
    fn a_write_replaces_every_file_and_leaves_nothing_else() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(dir.join("a.json"), "old a").unwrap();
        write_together(&[
            (dir.join("a.json"), b"new a".to_vec()),
            (dir.join("sub/b.yaml"), b"new b".to_vec()),
        ])
        .unwrap();
        assert_eq!(
            listing(dir),
            vec![("a.json".into(), b"new a".to_vec()), ("sub".into(), vec![])]
        );
        assert_eq!(std::fs::read(dir.join("sub/b.yaml")).unwrap(), b"new b");
    }

    /// An output inside the dataset folder is refused, whether named directly,
    /// through `..` or through a symlink to the folder; beside it is fine.
    #[test]
    fn an_output_inside_the_dataset_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = tmp.path().join("ds");
        std::fs::create_dir_all(ds.join("robot1")).unwrap();
        std::fs::write(ds.join("dataset.json"), "{}").unwrap();
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink(&ds, &link).unwrap();
        for out in [
            ds.join("dataset.json"),
            ds.join("robot1/captures.csv"),
            ds.join("new/RESULT.json"),
            tmp.path().join("x/../ds/RESULT.json"),
            link.join("RESULT.json"),
        ] {
            let e = refuse_output_over_input("--out", &out, Some(&ds), &[]).unwrap_err();
            assert!(e.to_string().contains("inside the dataset folder"), "{e}");
        }
        refuse_output_over_input("--out", &tmp.path().join("RESULT.json"), Some(&ds), &[]).unwrap();
        refuse_output_over_input("--out", &tmp.path().join("ds2/R.json"), Some(&ds), &[]).unwrap();
        let input = tmp.path().join("RESULT.json");
        std::fs::write(&input, "{}").unwrap();
        let e = refuse_output_over_input("--json", &link.join("../RESULT.json"), None, &[&input])
            .unwrap_err();
        assert!(e.to_string().contains("is the input"), "{e}");
    }
}
