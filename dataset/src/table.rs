//! Reading and writing the format's CSV files (`captures.csv`, `touch_points.csv`).
//!
//! Columns are found by name, not by position: a header must contain exactly the format's
//! columns (the optional board pose `ctx..cqw` as a block of seven), in any order, and
//! nothing else. A misspelt column is therefore an error at the header, not a silently
//! shifted number in every row. Cells are trimmed, a UTF-8 byte order mark (as some
//! spreadsheets write) is ignored, and quoting follows RFC 4180 through the `csv` crate,
//! so image paths may contain commas.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::error::{DatasetError, Location};

/// A CSV file split into a header and rows, with line numbers.
#[derive(Debug)]
pub(crate) struct Table {
    pub file: PathBuf,
    pub header: Vec<String>,
    pub header_line: u64,
    pub rows: Vec<Row>,
}

/// One data row.
#[derive(Debug)]
pub(crate) struct Row {
    /// 1-based, header excluded.
    pub row: usize,
    /// 1-based line of the file where the row starts.
    pub line: u64,
    pub fields: Vec<String>,
}

impl Row {
    pub fn at(&self, file: &Path, field: &str) -> Location {
        Location::cell(file, self.row, Some(self.line), field)
    }
}

/// The most data rows a table may have, and how to say so.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RowLimit {
    pub max: usize,
    /// What a row is, e.g. `pose rows`.
    pub what: &'static str,
    /// The constant that sets `max`.
    pub constant: &'static str,
    pub advice: &'static str,
}

/// Parses CSV bytes. `file` is only used in errors.
#[cfg(test)]
pub(crate) fn parse_table(bytes: &[u8], file: &Path) -> Result<Table, DatasetError> {
    parse_table_limited(bytes, file, None)
}

/// Parses CSV bytes, refusing more data rows than `limit` (reading stops at the
/// first row beyond it). `file` is only used in errors.
pub(crate) fn parse_table_limited(
    bytes: &[u8],
    file: &Path,
    limit: Option<RowLimit>,
) -> Result<Table, DatasetError> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    let mut header: Option<(Vec<String>, u64)> = None;
    let mut rows = Vec::new();
    for record in reader.records() {
        let record = record.map_err(|e| csv_error(file, &e))?;
        let line = record.position().map_or(0, |p| record_line(bytes, p));
        let fields: Vec<String> = record.iter().map(str::to_owned).collect();
        if header.is_none() {
            header = Some((fields, line));
        } else {
            if let Some(limit) = limit
                && rows.len() >= limit.max
            {
                return Err(DatasetError::TooManyRows {
                    file: file.to_owned(),
                    what: limit.what,
                    limit: limit.max,
                    constant: limit.constant,
                    advice: limit.advice,
                });
            }
            rows.push(Row {
                row: rows.len() + 1,
                line,
                fields,
            });
        }
    }
    let (header, header_line) = header.unwrap_or_default();
    Ok(Table {
        file: file.to_owned(),
        header,
        header_line: header_line.max(1),
        rows,
    })
}

/// The line a record starts on. The reader reports the position where it started
/// looking, which is before any blank lines it skipped; skip them here too.
fn record_line(bytes: &[u8], position: &csv::Position) -> u64 {
    let mut line = position.line();
    let start = usize::try_from(position.byte()).unwrap_or(usize::MAX);
    for &b in bytes.get(start..).unwrap_or_default() {
        match b {
            b'\n' => line += 1,
            b'\r' => {}
            _ => break,
        }
    }
    line
}

fn csv_error(file: &Path, e: &csv::Error) -> DatasetError {
    let mut at = Location::file(file);
    at.line = e.position().map(|p| p.line());
    let message = match e.kind() {
        csv::ErrorKind::Utf8 { err, .. } => {
            format!("field {} is not valid UTF-8", err.field() + 1)
        }
        _ => e.to_string(),
    };
    DatasetError::Csv { at, message }
}

/// Indices of the columns of a table.
#[derive(Debug)]
pub(crate) struct Columns {
    /// Index of each required column, in the order given.
    pub required: Vec<usize>,
    /// Index of each column of the optional block, when the block is present.
    pub block: Option<Vec<usize>>,
    /// Index of each optional single column, when present.
    pub optional: Vec<Option<usize>>,
}

/// Maps the header onto the expected columns.
pub(crate) fn map_columns(
    table: &Table,
    required: &[&str],
    block: &[&str],
) -> Result<Columns, DatasetError> {
    map_columns_optional(table, required, block, &[])
}

/// [`map_columns`] with optional single columns, anywhere in the header.
pub(crate) fn map_columns_optional(
    table: &Table,
    required: &[&str],
    block: &[&str],
    optional: &[&str],
) -> Result<Columns, DatasetError> {
    let expected = || {
        let mut s = required.join(",");
        if !block.is_empty() {
            s.push_str(&format!(" (optionally followed by {})", block.join(",")));
        }
        for name in optional {
            s.push_str(&format!(" (and optionally {name})"));
        }
        s
    };
    let at = |field: Option<&str>| {
        let mut at = Location::file(&table.file).at_line(table.header_line);
        at.field = field.map(str::to_owned);
        at
    };
    if table.header.is_empty() || table.header.iter().all(String::is_empty) {
        return Err(DatasetError::BadHeader {
            at: at(None),
            reason: format!("the file has no header; expected {}", expected()),
        });
    }
    let mut index: HashMap<&str, usize> = HashMap::new();
    for (i, name) in table.header.iter().enumerate() {
        if !required.contains(&name.as_str())
            && !block.contains(&name.as_str())
            && !optional.contains(&name.as_str())
        {
            let name = b2b_errors::excerpt(name);
            return Err(DatasetError::BadHeader {
                at: at(Some(&name)),
                reason: format!(
                    "unknown column `{name}` (column {}); expected {}",
                    i + 1,
                    expected()
                ),
            });
        }
        if let Some(first) = index.insert(name, i) {
            return Err(DatasetError::BadHeader {
                at: at(Some(name)),
                reason: format!(
                    "column `{name}` appears twice (columns {} and {})",
                    first + 1,
                    i + 1
                ),
            });
        }
    }
    let mut required_idx = Vec::with_capacity(required.len());
    for name in required {
        match index.get(name) {
            Some(&i) => required_idx.push(i),
            None => {
                return Err(DatasetError::BadHeader {
                    at: at(Some(name)),
                    reason: format!("column `{name}` is missing; expected {}", expected()),
                });
            }
        }
    }
    let present: Vec<Option<usize>> = block.iter().map(|n| index.get(n).copied()).collect();
    let block_idx = if present.iter().all(Option::is_none) {
        None
    } else if let Some(missing) = present.iter().position(Option::is_none) {
        return Err(DatasetError::BadHeader {
            at: at(Some(block[missing])),
            reason: format!(
                "column `{}` is missing: the columns {} come as a block of {}",
                block[missing],
                block.join(","),
                block.len()
            ),
        });
    } else {
        Some(present.into_iter().flatten().collect())
    };
    Ok(Columns {
        required: required_idx,
        block: block_idx,
        optional: optional.iter().map(|n| index.get(n).copied()).collect(),
    })
}

/// Checks a row has as many fields as the header.
pub(crate) fn check_field_count(table: &Table, row: &Row) -> Result<(), DatasetError> {
    if row.fields.len() == table.header.len() {
        return Ok(());
    }
    let mut at = Location::file(&table.file);
    at.row = Some(row.row);
    at.line = Some(row.line);
    Err(DatasetError::FieldCount {
        at,
        expected: table.header.len(),
        found: row.fields.len(),
    })
}

/// Parses one cell as a finite number.
pub(crate) fn number(
    file: &Path,
    row: &Row,
    index: usize,
    name: &str,
) -> Result<f64, DatasetError> {
    let text = &row.fields[index];
    let Ok(value) = text.parse::<f64>() else {
        let found = if text.is_empty() {
            "an empty cell".to_owned()
        } else {
            format!("`{}`", b2b_errors::excerpt(text))
        };
        return Err(DatasetError::BadNumber {
            at: row.at(file, name),
            found,
        });
    };
    if !value.is_finite() {
        return Err(DatasetError::NonFinite {
            at: row.at(file, name),
            value,
        });
    }
    Ok(value)
}

/// Renders rows as CSV (quoting where needed).
pub(crate) fn render(
    file: &Path,
    header: &[&str],
    rows: &[Vec<String>],
) -> Result<Vec<u8>, DatasetError> {
    let mut writer = csv::WriterBuilder::new().from_writer(Vec::new());
    let to_io = |e: csv::Error| DatasetError::io(file, std::io::Error::other(e.to_string()));
    writer.write_record(header).map_err(to_io)?;
    for row in rows {
        writer.write_record(row).map_err(to_io)?;
    }
    writer
        .into_inner()
        .map_err(|e| DatasetError::io(file, std::io::Error::other(e.to_string())))
}

#[cfg(test)]
mod tests {
    use super::*;

    const REQ: [&str; 3] = ["a", "b", "c"];
    const BLOCK: [&str; 2] = ["x", "y"];

    fn table(text: &str) -> Table {
        parse_table(text.as_bytes(), Path::new("/t.csv")).unwrap()
    }

    #[test]
    fn columns_any_order_with_block() {
        let t = table("\u{feff}c, a ,b,y,x\n1,2,3,4,5\n");
        let c = map_columns(&t, &REQ, &BLOCK).unwrap();
        assert_eq!(c.required, vec![1, 2, 0]);
        assert_eq!(c.block, Some(vec![4, 3]));
        assert_eq!(t.rows[0].fields, vec!["1", "2", "3", "4", "5"]);
    }

    #[test]
    fn header_problems() {
        for (text, needle) in [
            ("", "no header"),
            ("a,b\n", "`c` is missing"),
            ("a,b,c,x\n", "block of 2"),
            ("a,b,c,z\n", "unknown column `z`"),
            ("a,b,c,a\n", "appears twice"),
        ] {
            let e = map_columns(&table(text), &REQ, &BLOCK).unwrap_err();
            assert!(matches!(e, DatasetError::BadHeader { .. }), "{e}");
            assert!(e.to_string().contains(needle), "{text:?}: {e}");
            assert!(e.to_string().starts_with("/t.csv: line 1"), "{e}");
        }
    }

    #[test]
    fn rows_know_their_lines() {
        for text in [
            "a,b,c\n\n1,2,3\n\"x\ny\",2,3\n4,5,6\n",
            "a,b,c\r\n\r\n1,2,3\r\n\"x\r\ny\",2,3\r\n4,5,6",
            "\n\na,b,c\n1,2,3\n\n\n4,5,6\n7,8,9\n",
        ] {
            let t = table(text);
            let lines: Vec<_> = t.rows.iter().map(|r| (r.row, r.line)).collect();
            let header_first = t.header_line == 1;
            let expected = if header_first {
                vec![(1, 3), (2, 4), (3, 6)]
            } else {
                vec![(1, 4), (2, 7), (3, 8)]
            };
            assert_eq!(lines, expected, "{text:?}");
            assert_eq!(t.header_line, if header_first { 1 } else { 3 });
        }
    }

    #[test]
    fn invalid_utf8_is_an_error_with_line() {
        let e = parse_table(b"a,b,c\n1,\xff,3\n", Path::new("/t.csv")).unwrap_err();
        assert!(matches!(e, DatasetError::Csv { .. }));
        assert!(e.to_string().contains("line 2"), "{e}");
    }

    #[test]
    fn render_quotes_commas() {
        let out = render(Path::new("/t.csv"), &["a"], &[vec!["x,y".into()]]).unwrap();
        assert_eq!(String::from_utf8(out).unwrap(), "a\n\"x,y\"\n");
    }
}
