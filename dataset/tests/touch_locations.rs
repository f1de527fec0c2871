//! The optional `location` column of `touch_points.csv` (dataset-format.md): read,
//! and an empty location named by row.

use b2b_dataset::{DatasetError, read_touch_points};

#[test]
fn location_column_is_read_and_an_empty_one_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("touch_points.csv");
    std::fs::write(
        &file,
        "location,x1,y1,z1,x2,y2,z2\n\
         tip A,0.5,0.1,0.1,0.4,-0.1,0.1\n\
         tip A,0.5,0.1,0.1,0.4,-0.1,0.1\n\
         tip B,0.6,0.1,0.1,0.3,-0.1,0.1\n",
    )
    .unwrap();
    let pairs = read_touch_points(&file).unwrap();
    let locations: Vec<_> = pairs.iter().map(|p| p.location.as_deref()).collect();
    assert_eq!(locations, [Some("tip A"), Some("tip A"), Some("tip B")]);

    // Without the column: no locations.
    std::fs::write(&file, "x1,y1,z1,x2,y2,z2\n0.5,0.1,0.1,0.4,-0.1,0.1\n").unwrap();
    assert_eq!(read_touch_points(&file).unwrap()[0].location, None);

    std::fs::write(
        &file,
        "location,x1,y1,z1,x2,y2,z2\ntip A,0.5,0.1,0.1,0.4,-0.1,0.1\n ,0.5,0.1,0.1,0.4,-0.1,0.1\n",
    )
    .unwrap();
    let e = read_touch_points(&file).unwrap_err();
    assert!(matches!(e, DatasetError::EmptyLocation { .. }), "{e}");
    assert!(e.to_string().contains("row 2"), "{e}");
}
